"""Caustic removal: the FFT filter (``fft_filter``), the per-view estimate (``estimate``), the
RecGS loop (``recgs``), the paper's baselines (``baselines``), and the method interface the
``train`` command uses (``method``, ``build.make_method``)."""
