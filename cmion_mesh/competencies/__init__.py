"""Competencies shipped with cmion-mesh: CMION's test set and the simulated Spirit of the Building body."""
