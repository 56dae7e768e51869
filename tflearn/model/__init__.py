"""The model: shared torque fields (fields), per-motion weights and time profiles (weights),
and their torque program with the one model state (program)."""
