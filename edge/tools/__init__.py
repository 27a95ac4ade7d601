"""Tools around the daemon (benchmark, demo, collect mode); they drive it through its
public hooks."""
