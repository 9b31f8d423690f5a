"""The reference planner mind: the mind, its spec, its search."""
