"""The HTTP API, its request validation, the operator page, the live tactile feed and the
trace view."""
