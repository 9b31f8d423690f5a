"""Minds: CMION's demonstration minds, the planner mind, the FAtiMA connector."""
