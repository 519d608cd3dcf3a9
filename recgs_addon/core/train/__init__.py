"""Training: settings (``config``), the survey as the trainer sees it (``data``), what it fits
(``objective``, the seam the caustic methods fill), the loop (``trainer``, with its parts
``density_control``, ``evaluation`` and ``progress``), density control's operations
(``density``), losses and metrics (``losses``) and checkpoints (``checkpoint``)."""
