"""Modes (Kry et al. 2007): modal analysis (analysis), mode-driven motion (motion), the
``modes`` command and its config (command, config), and creatures that walk by their modes
(locomotion)."""
