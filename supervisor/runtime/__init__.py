"""The supervisor loop and what it needs at run time (event log, robot-state history)."""
