"""Fused kernels of the inference fast path (torch; Triton on CUDA): ``hr_stage`` (the HR stage of the guided
models: class-aware and joint bilateral upsampling, the network's residual head, the output transform,
remodulation and the pixel filter) and its Triton kernels ``hr_triton``."""
