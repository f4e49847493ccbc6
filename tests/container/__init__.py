"""Container task set tests (real processes on loopback)."""
