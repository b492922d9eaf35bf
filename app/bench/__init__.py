"""``isolume bench``: benchmarks that print figures (never timed assertions)."""
