"""Exceptions raised by the core. Every message names the file and the problem."""


class RecGSError(Exception):
    """Base class: a problem with the user's input that the user can fix."""


class SceneError(RecGSError):
    """A COLMAP model or its images cannot be used."""


class ImageError(RecGSError):
    """An image cannot be read or written."""


class PlyError(RecGSError):
    """A PLY file cannot be read or does not hold Gaussians."""


class VideoError(RecGSError):
    """A video clip cannot be read or gives no survey."""


class Cancelled(Exception):
    """The job was asked to stop (SIGTERM / SIGINT); not a fault of the input."""
