"""Nodes that belong to the whole graph rather than to one stage (power_node)."""
