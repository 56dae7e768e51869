"""Figures (figures) and animations (render)."""
