"""The simulator: synthetic RGB-D scenes of a person among occluders, seen by a robot camera."""
