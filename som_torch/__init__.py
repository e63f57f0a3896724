"""Tensorized self-organizing maps: many maps in parallel, masked inactive components."""
