"""Batch reconstruction of recorded capture sets: the per-set job that ``fringescope
reconstruct`` runs, and ``fringescope reprocess``, which runs it over whole recordings on
Dask distributed (an embedded local cluster or an existing scheduler).

Sits beside :mod:`app.api` above :mod:`app.service`: it reuses the service's calibration
carry-over rule and reads sets only through :func:`app.capture.read_capture_set`.
"""
