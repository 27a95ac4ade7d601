"""Evaluation: retrieval, Table I, Fig. 6, ablations, the VLM evaluation, the bench."""
