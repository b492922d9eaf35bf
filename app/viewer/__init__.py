"""``isolume view``: the window and its input, drawing, the lazy-bake client, surfaces off
the render thread, scripts and the panel."""
