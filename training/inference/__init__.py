"""Inference: loading a model for it (``loading``), the model ready to run (``model.InferenceModel``), the clip's
frames as inputs (``frames``, torch-free), the reference, fast, fused and graph paths (``fastpath``,
``frame_graph``), ONNX export (``export``) and the ONNX Runtime runner (``onnx_infer``, torch-free). This package's
``__init__`` imports nothing, so the torch-free modules load without torch (the add-on's preview)."""
