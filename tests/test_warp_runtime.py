"""Warp plumbing: kernels built aside in another process land in Warp's kernel cache."""

from __future__ import annotations

import sys
import textwrap

import pytest

from endogsim.warp_runtime import kernels_built_aside


def test_kernels_built_aside_land_in_the_kernel_cache_and_do_not_nest(tmp_path, monkeypatch):
    pkg = tmp_path / "src"
    pkg.mkdir()
    (pkg / "aside_kernels.py").write_text(textwrap.dedent("""
        import warp as wp

        @wp.kernel
        def double_it(a: wp.array(dtype=float)):
            i = wp.tid()
            a[i] = 2.0 * a[i]
    """))
    cache = tmp_path / "cache"
    monkeypatch.setenv("WARP_CACHE_PATH", str(cache))
    monkeypatch.setenv("PYTHONPATH", f"{pkg}:{':'.join(sys.path)}")
    with kernels_built_aside(["aside_kernels"]) as proc:
        assert proc is not None
        with kernels_built_aside(["aside_kernels"]) as inner:  # the demo's pipeline inside the demo
            assert inner is None
        assert proc.wait(timeout=300) == 0
    built = [p.name for p in cache.rglob("*.o") if "aside_kernels" in p.name]  # e.g. wp_aside_kernels_<hash>.cpu<hash>.o
    assert built, f"no native code built in {cache}: {[p.name for p in cache.rglob('*')]}"
    with kernels_built_aside([]) as nothing:
        assert nothing is None


@pytest.mark.parametrize("modules", [["no_such_module_anywhere"]])
def test_a_failed_aside_build_does_not_fail_the_body(modules):
    with kernels_built_aside(modules) as proc:
        assert proc.wait(timeout=300) != 0  # the body goes on and builds its kernels itself
