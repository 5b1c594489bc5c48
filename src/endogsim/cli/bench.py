"""``endogsim bench ...``: the benchmark commands. Each prints a table and, with ``--json``, writes it.

The measurements live in :mod:`endogsim.bench` (render, mpm, identify, suite, convergence); this module only parses the
options, shows progress and prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from endogsim.bench.identify import SCENES_CACHE
from endogsim.bench.suite import DEFAULT_ITERS, RUN_KEYS
from endogsim.cli.common import console, print_table, progress, user_errors
from endogsim.identify.config import DEFAULT_REFINED_CORRECTION
from endogsim.io.atomic import write_json_atomic


def parse_counts(text: str, option: str) -> list[int]:
    """Comma-separated whole numbers >= 1 (e.g. ``--threads 1,2``), or a clear error naming ``option``."""
    try:
        counts = [int(v) for v in text.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise typer.BadParameter(f"{option} {text!r}: comma-separated whole numbers >= 1, e.g. 1,2")
    return counts


def register(bench_app: typer.Typer) -> None:
    """Add ``render``, ``mpm``, ``identify``, ``suite`` and ``convergence`` to the ``bench`` sub-app."""

    @bench_app.command("render")
    @user_errors
    def bench_render(
        json_path: Optional[Path] = typer.Option(None, "--json", help="Also write the results to this JSON file."),
        repeats: int = typer.Option(3, help="Timed repetitions per case (median reported), after one warm-up."),
        max_gaussians: int = typer.Option(200_000, help="Skip cases with more Gaussians than this."),
    ) -> None:
        """Forward and forward+backward time and peak memory of the renderer (5k/50k/200k Gaussians)."""
        import torch

        from endogsim.bench.render import CASES, run_case_subprocess
        from endogsim.gaussians.backend_gsplat import available

        backends = ["torch", "warp"] + (["gsplat"] if available() else [])
        todo = [(b, *c) for b in backends for c in CASES if c[0] <= max_gaussians]
        results = []
        with progress() as bar:
            task = bar.add_task("bench render", total=len(todo))
            for backend, n, w, h in todo:
                results.append(run_case_subprocess(n, w, h, backend, repeats))
                bar.advance(task)
        print_table(
            "Gaussian renderer (peak memory: CPU = process peak RSS incl. ~0.3 GB for python+torch; CUDA = max allocated)",
            ["backend", "gaussians", "resolution", "forward s", "fwd+bwd s", "peak MB", "pairs"],
            [(r["backend"], r["gaussians"], f"{r['width']}x{r['height']}", r["forward_s"], r["forward_backward_s"],
              r["peak_mem_mb"], r["pairs"]) for r in results],
        )
        if json_path is not None:
            write_json_atomic(json_path, {"cases": results, "threads": torch.get_num_threads()})

    @bench_app.command("mpm")
    @user_errors
    def bench_mpm(
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the table as JSON {\"cases\": [...]} here."),
        sizes: str = typer.Option("8000,32768,128000", help="Particle counts (comma separated)."),
        frames: int = typer.Option(2, help="Frames (25 substeps each) timed per case."),
        mem_frames: int = typer.Option(20, help="Frames of the full-mode memory run at 32k particles."),
        no_memory: bool = typer.Option(False, "--no-memory", help="Skip the full-mode peak-memory run."),
        device: str = typer.Option("auto", help="cpu, cuda, or auto (cpu plus cuda when available)."),
        threads: Optional[str] = typer.Option(None, "--threads", help="Torch thread counts to measure each case "
                                              "at, side by side (comma separated; default: the process's)."),
    ) -> None:
        """Forward / backward throughput of the MPM simulator and full-mode peak memory."""
        import warp as wp

        from endogsim.bench.mpm import run_bench
        from endogsim.warp_runtime import init_warp

        init_warp()
        devices = ["cpu", "cuda"] if device == "auto" and wp.is_cuda_available() else (["cpu"] if device == "auto" else [device])
        counts = [int(s) for s in sizes.split(",") if s.strip()]
        thread_counts = None if threads is None else parse_counts(threads, "--threads")
        cases = run_bench(counts, frames, mem_frames, devices, memory=not no_memory, threads=thread_counts)
        cols = ["device", "particles", "grid", "threads", "forward_pss", "backward_pss", "backward_over_forward",
                "peak_mem_mb"]
        labels = ["device", "particles", "grid", "threads", "fwd p-sub/s", "fwd+bwd p-sub/s", "bwd/fwd",
                  f"peak MB ({mem_frames} fr full)"]
        print_table("MLS-MPM (Warp): particle-substeps/s, backward in frame mode", labels,
                    [[("-" if c[k] is None else c[k]) for k in cols] for c in cases])
        if json_path is not None:
            write_json_atomic(json_path, {"cases": cases})
            console.print(f"wrote {json_path}")

    @bench_app.command("identify")
    @user_errors
    def bench_identify(
        json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the tables and runs as JSON."),
        quick: bool = typer.Option(False, "--quick", help="tiny (and a small two_tissues), 6 iterations (minutes on CPU)."),
        iters: Optional[int] = typer.Option(None, "--iters", help="Iterations per optimised run."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Identify from the first N frames only."),
        scenes: Optional[str] = typer.Option(None, "--scenes", help="Comma-separated scenes for the tables."),
        tables: Optional[str] = typer.Option(None, "--tables", help="Comma-separated subset of init,field,loss,grad."),
        scenes_dir: Path = typer.Option(SCENES_CACHE, "--scenes-dir",
                                        help="Where benchmark scenes are synthesized (reused)."),
        work_dir: Path = typer.Option(Path("bench_identify_runs"), "--work-dir", help="Run folders of the ablations."),
    ) -> None:
        """Identification ablations: init x optimisation, material field vs global, loss, gradient mode."""
        from endogsim.bench.identify import run_bench

        res = run_bench(scenes_dir, work_dir, quick=quick, iters=iters, frames=frames,
                        scenes=scenes.split(",") if scenes else None, tables=tables.split(",") if tables else None,
                        log=console.print)
        for t in res["tables"].values():
            print_table(t["title"], t["columns"], t["rows"])
        if json_out is not None:
            write_json_atomic(json_out, res)
            console.print(f"wrote {json_out}")

    @bench_app.command("suite")
    @user_errors
    def bench_suite(
        json_out: Optional[Path] = typer.Option(None, "--json", help="Also write settings, per-scene runs and tables as JSON."),
        ray: bool = typer.Option(False, "--ray", help="Run the scenes in parallel as Ray tasks (a local cluster "
                                 "unless --ray-address is given)."),
        ray_address: Optional[str] = typer.Option(None, "--ray-address",
                                                  help="Ray cluster address (e.g. ray://host:10001 or auto); implies --ray."),
        scenes: Optional[str] = typer.Option(None, "--scenes", help="Comma-separated suite scenes (default: all but "
                                             "the small scenes tiny and tiny_lift)."),
        iters: Optional[int] = typer.Option(None, "--iters", help=f"Iterations of the optimised runs (default "
                                            f"{DEFAULT_ITERS}; quick 2)."),
        runs: Optional[str] = typer.Option(None, "--runs", help=f"Comma-separated runs to do, of {', '.join(RUN_KEYS)} "
                                           "(default all; the full method alone: prior_on)."),
        time_budget: Optional[float] = typer.Option(None, "--time-budget", help="Stop each identification after "
                                                    "this many seconds (default: no stop, so that the figures do "
                                                    "not depend on the machine's speed)."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Frames per synthesized scene (default: the suite's)."),
        optimizer: str = typer.Option("rprop", "--optimizer", help="Identification's optimiser: rprop (the "
                                      "suite's figures) | adam | lm (Levenberg-Marquardt)."),
        refine: float = typer.Option(1.0, "--refine", help="Identify at the scenes' identification discretisation "
                                     "refined by this factor (grid x F, particle spacing / F, substeps x F; up to "
                                     "F^4 the time). Below 2, the ground truth's."),
        refined_correction: Optional[float] = typer.Option(
            None, "--refined-correction", help="Correct what the video determines to the discretisation refined this "
            "many times more (0: none; default: identification's 1.5 at --refine 1, none at a finer --refine). Times "
            "--refine, below 2, the ground truth's."),
        device: str = typer.Option("cpu", "--device", help="Identification's simulator and renderer: cpu | cuda "
                                   "(the ground truth is synthesized on the CPU)."),
        quick: bool = typer.Option(False, "--quick", help="tiny, 4 frames, 2 iterations: a smoke run (minutes)."),
        fresh: bool = typer.Option(False, "--fresh", help="Run every scene again (by default a scene whose record in "
                                   "the work folder was made with the same settings, scene and code is reused)."),
        seed: int = typer.Option(0, "--seed", help="Every scene's texture, relief and noise (default 0, the figures "
                                 "of record): the same experiments on other surfaces. A scene whose ground truth "
                                 "the generator refuses at this seed is left out and named."),
        fid_weights: Optional[Path] = typer.Option(None, "--fid-weights", help="Local Inception-v3 weights for FID."),
        threads: Optional[int] = typer.Option(None, "--threads", help="Torch threads in this process (Ray tasks use 1)."),
        workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Simulations run side by side (default: "
                                              "one per torch thread). The results do not depend on it."),
        scenes_dir: Path = typer.Option(SCENES_CACHE, "--scenes-dir",
                                        help="Where scenes are synthesized (reused)."),
        work_dir: Path = typer.Option(Path("bench_suite_runs"), "--work-dir", help="Run folders."),
    ) -> None:
        """The benchmark suite: Table 2 (RE/EPE per scene), Table 3 (init x optimisation, RE/EPE/FID) and the
        material-field ablation."""
        from endogsim.bench.suite import run_suite

        use_ray = ray or ray_address is not None
        if refined_correction is None:
            refined_correction = DEFAULT_REFINED_CORRECTION if refine == 1.0 else 0.0
        res = run_suite(scenes.split(",") if scenes else None, scenes_dir, work_dir, iters=iters, quick=quick,
                        frames=frames, fid_weights=str(fid_weights) if fid_weights else None, ray=use_ray,
                        ray_address=ray_address, threads=threads, runs=runs.split(",") if runs else None,
                        time_budget=time_budget, optimizer=optimizer, refine=refine,
                        refined_correction=refined_correction or None, device=device, fresh=fresh, workers=workers,
                        seed=seed, log=console.print)
        for t in res["tables"].values():
            print_table(t["title"], t["columns"], t["rows"])
            if t.get("note"):
                console.print(f"  ({t['note']})")
        console.print(f"suite wall time {res['wall_seconds']:.1f} s ({'ray' if use_ray else 'in-process'}), seed {seed}"
                      + (f"; left out (ground truth refused): {', '.join(res['refused'])}" if res["refused"] else ""))
        if json_out is not None:
            write_json_atomic(json_out, res)
            console.print(f"wrote {json_out}")

    @bench_app.command("convergence")
    @user_errors
    def bench_convergence(
        json_out: Optional[Path] = typer.Option(None, "--json", help="Also write {\"cases\": [...], \"settings\"} here."),
        scenes: Optional[str] = typer.Option(None, "--scenes", help="Comma-separated suite scenes (default: all)."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Simulate only the first N frames (default: "
                                             "each scene's)."),
        factor: int = typer.Option(2, "--factor", help="Refinement factor (grid x factor, particle spacing / "
                                   "factor, substeps x factor at least)."),
        levels: Optional[str] = typer.Option(None, "--levels", help="Instead: a refinement sequence, e.g. 1,2,3: "
                                             "the RMS change from each level to the next (does it fall?)."),
        refine: str = typer.Option("grid,particles,substeps", "--refine", help="What the factor refines "
                                   "(comma-separated): e.g. substeps alone asks whether the motion is converged "
                                   "in time at identification's grid; grid alone takes the substeps its CFL rule "
                                   "asks for."),
        seed: int = typer.Option(0, "--seed", help="Every scene's texture and relief (default 0, the figures of "
                                 "record)."),
    ) -> None:
        """Is identification's discretisation converged? Each scene's ground-truth simulation at identification's
        grid, particles and substeps vs refined 2x: the RMS change of the tissue's motion (target <= 0.05)."""
        from endogsim.bench.convergence import TARGET_RMS_CHANGE, run_bench
        from endogsim.synth.suite import suite_scene_names

        parts = tuple(p.strip() for p in refine.split(",") if p.strip())
        names = scenes.split(",") if scenes else suite_scene_names()
        if frames is not None and frames < 2:
            raise typer.BadParameter("--frames must be >= 2")
        if levels is not None:
            steps = parse_counts(levels, "--levels")
            res = run_bench(names, frames, log=console.print, levels=steps, refine=parts, seed=seed)
            print_table(f"Refinement sequence {' -> '.join(f'{f}x' for f in steps)}: RMS motion change from each "
                        "level to the next",
                        ["scene", "particles", "grid", "rms motion (mm)", "rms changes", "seconds"],
                        [(q["scene"], " / ".join(map(str, q["particles"])), " / ".join(map(str, q["grid"])),
                          " / ".join(f"{v:.3f}" for v in q["rms_motion_mm"]),
                          ", ".join(f"{c:.3f}" for c in q["changes"]), f"{sum(q['seconds']):.0f}")
                         for q in res["sequences"]])
            if json_out is not None:
                write_json_atomic(json_out, res)
                console.print(f"wrote {json_out}")
            return
        res = run_bench(names, frames, factor=factor, log=console.print, refine=parts, seed=seed)
        print_table(f"Discretisation convergence: motion change under a {factor}x refinement of the "
                    f"{', '.join(parts)} (target rms change <= {TARGET_RMS_CHANGE})",
                    ["scene", "particles", "grid", "substeps", "refined grid", "refined particles",
                     "refined substeps", "rms motion (mm)", "default's rms motion (mm)", "rms change", "seconds",
                     "refined seconds"],
                    [(c["scene"], c["particles"], c["grid"], c["substeps"], c["refined_grid"], c["refined_particles"],
                      c["refined_substeps"], c["rms_motion_mm"], c["rms_motion_default_mm"], c["rms_change"],
                      c["seconds"], c["refined_seconds"])
                     for c in res["cases"]])
        over = [c["scene"] for c in res["cases"] if not c["converged"]]
        console.print(f"{len(res['cases']) - len(over)}/{len(res['cases'])} scenes within the target"
                      + (f"; not converged: {', '.join(over)}" if over else ""))
        if json_out is not None:
            write_json_atomic(json_out, res)
            console.print(f"wrote {json_out}")
