"""Drawing: GL contexts, the surface renderer and its lattice textures, the camera,
pictures on disk, off-screen renders and the view's traced global illumination."""
