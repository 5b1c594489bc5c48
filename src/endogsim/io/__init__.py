"""Scene I/O: dataset loaders, label tables and video writing."""

from endogsim.io.loaders import detect_format, load_cholecseg8k, load_endonerf, load_scene, load_video
from endogsim.io.scene import ObjectLabel, Scene
from endogsim.io.video_writer import write_frames_png, write_video

__all__ = ["Scene", "ObjectLabel", "load_scene", "load_endonerf", "load_cholecseg8k", "load_video",
           "detect_format", "write_video", "write_frames_png"]
