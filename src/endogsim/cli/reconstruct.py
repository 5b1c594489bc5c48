"""``endogsim reconstruct``: 4D Gaussian reconstruction of an endoscopic video (Endo-4DGS style)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from endogsim.cli.common import output_folder, user_errors


def register(app: typer.Typer) -> None:
    """Add ``reconstruct`` to ``app``."""

    @app.command("reconstruct")
    @user_errors
    def reconstruct_cmd(
        data: Path = typer.Argument(..., help="EndoNeRF / CholecSeg8K / procedural folder, or a video file."),
        out: Path = typer.Option(..., "--out", "-o", callback=output_folder,
                                 help="Run folder (outputs, checkpoint; resumes if present)."),
        config: Optional[Path] = typer.Option(None, "--config", help="JSON or TOML file of ReconConfig options."),
        resolution_scale: Optional[float] = typer.Option(None, "--resolution-scale",
                                                         help="Training image scale (default 0.5 on CPU, 1 on GPU)."),
        iters: Optional[int] = typer.Option(None, "--iters", help="Total iterations (coarse + deformation)."),
        time_budget: Optional[float] = typer.Option(None, "--time-budget",
                                                    help="Safety stop: stop training after this many seconds and "
                                                         "export (the schedule follows --iters only)."),
        device: str = typer.Option("auto", "--device", help="auto, cpu or cuda."),
        max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Use only the first frames."),
        depth_method: Optional[str] = typer.Option(None, "--depth-method",
                                                   help="auto, dataset, pi3, depth_anything or fallback."),
        depth_weights: Optional[str] = typer.Option(None, "--depth-weights", help="Local weights of the depth model."),
        seg_method: Optional[str] = typer.Option(None, "--seg-method", help="auto, dataset, sam2 or fallback."),
        seg_checkpoint: Optional[str] = typer.Option(None, "--seg-checkpoint", help="Local SAM 2 checkpoint (.pt)."),
        seg_config: Optional[str] = typer.Option(None, "--seg-config", help="sam2 model config of the checkpoint."),
        flow_method: Optional[str] = typer.Option(None, "--flow-method",
                                                  help="Optical flow for the point tracks: dis (offline), dis_fine, "
                                                       "raft (needs --flow-weights) or none (no tracks)."),
        flow_weights: Optional[str] = typer.Option(None, "--flow-weights", help="Local RAFT weights (.pth)."),
        camera_motion: Optional[str] = typer.Option(None, "--camera-motion",
                                                    help="auto, on or off: learn a pose per frame for a moving "
                                                         "endoscope (auto: when the data has neither poses nor depth)."),
        fresh: bool = typer.Option(False, "--fresh", help="Ignore an existing checkpoint in --out."),
    ) -> None:
        """Reconstruct deformable tissue + rigid tools as Gaussians; write PLY, deformation, trajectories,
        test renders and metrics.json (PSNR/SSIM, masked and EndoNeRF protocols)."""
        import torch

        from endogsim.cli.common import console, print_table, progress
        from endogsim.recon.config import load_config
        from endogsim.recon.train import reconstruct

        dev = ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device
        cfg = load_config(config, defaults_for=dev, resolution_scale=resolution_scale, iters=iters, device=dev,
                          time_budget_s=time_budget,
                          max_frames=max_frames, depth_method=depth_method, depth_weights=depth_weights,
                          seg_method=seg_method, seg_checkpoint=seg_checkpoint, seg_config=seg_config,
                          point_tracks=None if flow_method is None else flow_method != "none",
                          flow=None if flow_method in (None, "none") else {"method": flow_method, "weights": flow_weights},
                          camera_motion=camera_motion)
        with progress() as bar:
            task = bar.add_task("reconstruct", total=cfg.iters)

            def cb(it: int, total: int, info: dict) -> None:
                bar.update(task, completed=it,
                           description=f"reconstruct (loss {info['loss']:.4f}, {info['n']} Gaussians)")

            m = reconstruct(data, out, cfg, progress=cb, resume=not fresh)
        interpolated = ([("PSNR masked, interpolated test poses (dB)", m["psnr_masked_interpolated_pose"])]
                        if "psnr_masked_interpolated_pose" in m else [])
        print_table(f"Reconstruction of {data} ({m['resolution'][0]}x{m['resolution'][1]}, test frames "
                    f"{m['test_frames']})", ["metric", "value"],
                    [("PSNR masked (dB)", m["psnr_masked"]), *interpolated,
                     ("PSNR EndoNeRF protocol (dB)", m["psnr_endonerf"]),
                     ("SSIM masked", m["ssim_masked"]), ("SSIM EndoNeRF protocol", m["ssim_endonerf"]),
                     ("training seconds", m["training_seconds"]), ("iterations", m["iterations"]),
                     ("Gaussians", m["num_gaussians"]),
                     ("depth prior", m["depth_source"]), ("segmentation", m["segmentation_source"]),
                     ("point tracks", m["track_source"] if m["track_source"] == "none" else
                      f"{m['track_source']} ({m['init'].get('tracked_share', 0):.0%} of Gaussian-frames)"),
                     ("camera", ("moving (learnt poses, test poses registered)" if "pose_alignment" in m else
                                "moving (learnt poses)") if m["camera_motion"] else "fixed"),
                     ("tissue share of test pixels", m["tissue_pixel_fraction"])])
        console.print(f"wrote {out}")
