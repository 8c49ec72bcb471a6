"""BlendSR's torch layer: training data from clips, the models, training, evaluation and benchmarks.

Importing this package imports nothing heavy; torch is needed by the modules that train or run models.
``docs/training.md`` (training) and ``docs/evaluation.md`` (evaluation, inference, benchmarks) describe the layer.
"""
