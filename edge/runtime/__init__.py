"""What `vt-edge run` is: lifecycle, sensor path, ring, press, recognition, compute process,
episode store, metrics, and the domain types they share. Nothing here knows how people or
machines reach it (edge.interfaces) or what records it (edge.recordings)."""
