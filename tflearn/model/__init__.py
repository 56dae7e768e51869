"""The model: shared torque fields, per-motion weights and their torque program (fields)."""
