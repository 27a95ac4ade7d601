"""What ships: ONNX export, the reference database, the manifest, release and build."""
