"""The model: cameras (``cameras``), Gaussians (``gaussians``) and their spherical-harmonic
colours (``sh``). Plain numpy but for ``sh`` (torch)."""
