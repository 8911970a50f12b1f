"""Shared contracts at the bottom of the layers: every other package takes these facts from here."""
