"""``isolume chart``: speed against accuracy, charted."""
