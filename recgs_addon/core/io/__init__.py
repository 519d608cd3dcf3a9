"""Reading and writing things: COLMAP surveys (``colmap``), images (``images``, OpenImageIO),
3DGS PLY files (``ply``), a survey's frame times (``frames``) and baking a similarity
transform into Gaussians (``transform``). No torch."""
