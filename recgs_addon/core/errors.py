"""Exceptions raised by the core. Every message names the file and the problem."""


class RecGSError(Exception):
    """Base class: a problem with the user's input that the user can fix."""


class SceneError(RecGSError):
    """A COLMAP model or its images cannot be used."""


class ImageError(RecGSError):
    """An image cannot be read or written."""


class PlyError(RecGSError):
    """A PLY file cannot be read or does not hold Gaussians."""
