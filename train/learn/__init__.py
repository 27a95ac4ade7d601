"""Learning: press data, the GRU VQ-VAE, its trainer."""
