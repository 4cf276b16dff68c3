"""The data contract: `layout` (paths, file formats, JSON builders; numpy only) and `load` (a typed
`Dataset` of torch tensors). `load_dataset` and the `load` types are imported on first use, so the
dataset generator can use `layout` without importing torch."""

_LOAD = ("BedInfo", "Dataset", "GroundTruth", "SPLITS", "View", "load_dataset")
__all__ = list(_LOAD)


def __getattr__(name: str):
    if name in _LOAD:
        from ragsplat.dataset import load

        return getattr(load, name)
    raise AttributeError(f"module 'ragsplat.dataset' has no attribute {name!r}")
