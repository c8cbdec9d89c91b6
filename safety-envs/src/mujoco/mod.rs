//! Safe wrapper over `mujoco-sys` (filled in by the foundation issue).
