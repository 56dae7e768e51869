"""Motion capture: BVH files (bvh), arm maps and retargeting (retarget), bodies from a BVH hierarchy
(skeleton), and clip import/export (clips)."""
