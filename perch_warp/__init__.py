"""perch_warp: RGB-only (x, y, yaw) pose search of a known object on a table (PERCH Color Only) on NVIDIA Warp.

    from perch_warp import Engine, EngineConfig, load_mesh, load_feature_weights
    engine = Engine(load_mesh("obj.obj"), load_feature_weights("auto"), device="cuda:0")
    result = engine.estimate(image, camera, table, resting, space)

Heavy modules (Warp, torch) load on first use of these names.
"""

__version__ = "0.1.0"

_LAZY = {
    "Engine": "engine",
    "EngineConfig": "engine",
    "Result": "result",
    "Camera": "camera",
    "Table": "table",
    "RestingPose": "table",
    "SearchSpace": "search_space",
    "load_mesh": "mesh",
    "load_rgb": "image",
    "load_feature_weights": "features",
    "PerchError": "errors",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
