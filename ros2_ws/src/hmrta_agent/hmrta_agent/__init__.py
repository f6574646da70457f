"""HMRTA agent: one decision maker per robot (see agent_node)."""
