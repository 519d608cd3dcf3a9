"""Reading and writing things: COLMAP surveys (``colmap``), images (``images``, OpenImageIO),
3DGS PLY files (``ply``), structure from motion (``sfm``, pycolmap) and baking a similarity
transform into Gaussians (``transform``). No torch."""
