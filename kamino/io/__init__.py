"""Model import: MJCF through the mujoco package's own parser (docs/mjcf.md)."""

from kamino.io.mjcf import MjcfImport, MjcfJoint, import_mjcf, load_mjcf

__all__ = ["MjcfImport", "MjcfJoint", "import_mjcf", "load_mjcf"]
