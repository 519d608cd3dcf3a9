"""Rendering: projection of Gaussians to the image (``projection``), the differentiable tile
rasterizer (``rasterizer.render``), and row-sparse gradient gathering (``rowgrads``)."""
