"""Training: settings (``config``), the survey as the trainer sees it (``data``), what it fits
(``objective``, the seam the caustic methods fill), the loop (``trainer``), density control
(``density``), losses and metrics (``losses``) and checkpoints (``checkpoint``)."""
