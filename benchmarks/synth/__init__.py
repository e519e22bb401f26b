"""Making data: Cycles render speed, and the per-pixel observation maps against Cycles."""
