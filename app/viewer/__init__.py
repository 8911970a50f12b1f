"""The 3-D viewer (viser) and its relay under ``/viser/``; the only package importing viser.

``from app.viewer.viewer import Viewer`` and ``from app.viewer.relay import viewer_router``;
:mod:`app.viewer.cloud` (numpy/OpenCV only) turns results into point-cloud arrays.
Nothing is imported here, so importing the package does not start viser.
"""
