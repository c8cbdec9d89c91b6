//! MJCF models of the robots and arenas used by `safety-envs`, embedded at
//! compile time so binaries do not depend on the working directory.
