"""Long-running end-to-end checks (kept small enough for the default run)."""
