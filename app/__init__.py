"""isolume's application layer: GL contexts, renderer, viewer and the command line.

Imports `volumes` and `baking` (public API only); nothing imports `app`.
"""
