"""Lab work: collect mode, plans, datasets, the press recorder, consistency, the demo, the
emulated robot and daemon as processes."""
