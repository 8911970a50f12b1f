"""Outputs beside the API, each reading the service's result slot.

- :mod:`app.outputs.viewer` — the 3-D viewer (viser; the only module importing viser) and
  :mod:`app.outputs.relay`, its relay under ``/viser/``; :mod:`app.outputs.cloud` (numpy/OpenCV
  only) turns results into point-cloud arrays.
- :mod:`app.outputs.igtl` — the OpenIGTLink server and the POLYDATA codec for pyigtl clients
  (``from app.outputs.igtl import register_codecs``).
- :mod:`app.outputs.encoding` — depth/sigma/texture images (PNG, colour maps) the API serves.

Outputs import the service and below, never :mod:`app.api`. Nothing is imported here, so
importing the package does not start viser.
"""
