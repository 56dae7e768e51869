"""Physics: immutable kinematic trees (body), configuration-space operations (configspace),
compiled kernels (kernels), batched rigid-body dynamics (dynamics) and ground contact (contact)."""
