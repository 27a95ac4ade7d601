"""vtzero offline training: VQ-VAE tactile encoder, ONNX export, reference database."""

import edge  # noqa: F401  (sets ORT_DISABLE_TELEMETRY before onnxruntime is imported)
