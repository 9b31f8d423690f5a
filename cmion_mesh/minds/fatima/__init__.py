"""The original FAtiMA mind over CMION's agent-mind line protocol."""
