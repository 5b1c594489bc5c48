"""Scene I/O: dataset formats and loaders, label tables, atomic writes and video writing.

Names load lazily (PEP 562): lower layers import :mod:`endogsim.io.atomic` without pulling in OpenCV.
"""

from importlib import import_module

_EXPORTS = {
    "Scene": "scene", "ObjectLabel": "scene",
    "load_scene": "formats", "load_endonerf": "loaders", "load_cholecseg8k": "loaders", "load_video": "loaders",
    "detect_format": "formats", "register_format": "formats", "DatasetFormat": "formats", "FORMATS": "formats",
    "write_video": "video_writer", "write_frames_png": "video_writer",
    "write_json_atomic": "atomic", "save_torch_atomic": "atomic", "save_npz_atomic": "atomic",
    "write_text_atomic": "atomic", "atomic_path": "atomic", "atomic_folder": "atomic",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f"endogsim.io.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'endogsim.io' has no attribute {name!r}")
