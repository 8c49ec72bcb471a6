"""BlendSR's torch layer: training data from clips, the models, training, evaluation and benchmarks.

Importing this package imports nothing heavy; torch is needed by the modules that train or run models.
``docs/training.md`` (training) and ``docs/evaluation.md`` (evaluation, inference, benchmarks) describe the layer.
"""
import importlib

__all__ = ["load_config", "load_model", "evaluate_model", "MODELS"]

#: the package's public names, imported when first used (``import training`` stays light). Training itself is
#: ``training.train.train(load_config(...), RUN)`` (not re-exported: the name is also the submodule's).
_LAZY = {"load_config": ".config", "load_model": ".inference", "evaluate_model": ".evaluate", "MODELS": ".models"}


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
