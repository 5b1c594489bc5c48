"""``endogsim materials init`` and ``endogsim materials show``."""

from __future__ import annotations

import warnings
from pathlib import Path

import typer

from endogsim.cli.common import console, err_console, print_table, user_errors


def _table(field, title: str) -> None:
    from rich.markup import escape  # names and fallback reasons may contain [brackets]

    rows = [(r.object_id, escape(r.name), r.klass, r.model, "yes" if r.rigid else "no", f"{r.E:.3g}", f"{r.nu:.3f}",
             f"{r.density:.0f}", "" if r.E_min is None else f"{r.E_min:.2g}-{r.E_max:.2g}",
             "" if r.confidence is None else f"{r.confidence:.2f}", escape(r.source)) for r in field.records]
    print_table(escape(title), ["id", "name", "class", "model", "rigid", "E (Pa)", "nu", "rho (kg/m^3)", "E range (Pa)",
                        "conf.", "source"], rows)


def register(app: typer.Typer) -> None:
    """Add ``init`` and ``show`` to the ``materials`` sub-app."""

    @app.command("init")
    @user_errors
    def init(
        data_or_run: Path = typer.Argument(..., help="Data folder, run folder (labels.json / scene.json) or labels.json."),
        backend: str = typer.Option("prior", "--backend", "-b", help="manual | prior | mllm | replay"),
        out: Path = typer.Option(Path("materials.json"), "--out", "-o", help="Output material field (JSON, SI units)."),
        regime: str = typer.Option("in_vivo", help="Prior column / prompt regime: in_vivo | ex_vivo_tensile."),
        model: str = typer.Option("gpt-4o", help="MLLM model name (mllm/replay)."),
        base_url: str = typer.Option(None, help="OpenAI-compatible endpoint, e.g. http://localhost:8000/v1 (vLLM, "
                                     "Ollama, llama.cpp, LM Studio). Default: api.openai.com. Key: env "
                                     "ENDOGSIM_MLLM_API_KEY or OPENAI_API_KEY."),
        cache: Path = typer.Option(None, help="MLLM answer cache folder (default: <out folder>/mllm_cache)."),
        timeout: float = typer.Option(60.0, help="Per-request timeout in seconds."),
        total_timeout: float = typer.Option(300.0, help="Bound on the seconds of all MLLM requests together; "
                                            "objects left when it is used up take the prior."),
        manual_E: float = typer.Option(1e4, "--manual-E", help="manual backend: E in Pa."),
        manual_nu: float = typer.Option(0.45, "--manual-nu", help="manual backend: Poisson ratio."),
        manual_density: float = typer.Option(1000.0, "--manual-density", help="manual backend: kg/m^3."),
        downscale: float = typer.Option(None, help="Frame downscale when reading a data folder."),
    ) -> None:
        """Initialise the object-wise material field and write it to --out."""
        from endogsim.materials import (
            ManualMaterial,
            MaterialInitConfig,
            MLLMConfig,
            initialise_materials,
            load_objects,
        )
        from endogsim.materials.field import MaterialRecord

        # Validate the manual value up front so a bad number is reported as such.
        MaterialRecord(name="manual", object_id=0, klass="manual", E=manual_E, nu=manual_nu, density=manual_density)
        labels, scene = load_objects(data_or_run, need_images=backend in ("mllm", "replay"), downscale=downscale)
        cfg = MaterialInitConfig(
            backend=backend, regime=regime,  # type: ignore[arg-type]
            manual=ManualMaterial(E=manual_E, nu=manual_nu, density=manual_density),
            mllm=MLLMConfig(model=model, base_url=base_url, timeout_s=timeout, total_timeout_s=total_timeout,
                            cache_dir=cache if cache is not None else out.parent / "mllm_cache"),
        )
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            field = initialise_materials(labels, cfg, scene)
        for w in caught:
            err_console.print(f"[yellow]warning:[/] {w.message}", highlight=False)
        field.save(out)
        _table(field, f"materials ({backend}, {regime})")
        console.print(f"wrote {out}")

    @app.command("show")
    @user_errors
    def show(path: Path = typer.Argument(..., help="A material field JSON written by `materials init`.")) -> None:
        """Print a material field as a table."""
        from endogsim.materials import MaterialField

        _table(MaterialField.load(path), str(path))
