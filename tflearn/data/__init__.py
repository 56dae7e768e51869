"""Data: motions tflearn makes (gestures, keyframes) and what a config's ``data`` names (loading)."""
