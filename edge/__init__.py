"""vtzero on-robot runtime: press, tactile encoding, VLM recognition. Never imports torch."""

__version__ = "0.1.0"
