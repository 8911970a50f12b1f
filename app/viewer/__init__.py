"""The 3-D viewer (viser) and its relay under ``/viser/``; the only package importing viser.

``from app.viewer.viewer import Viewer`` and ``from app.viewer.relay import viewer_router``;
:mod:`app.viewer.colormap` (numpy/OpenCV only) holds the depth colormap shared with the
dashboard. Nothing is imported here, so the colormap does not pull in viser.
"""
