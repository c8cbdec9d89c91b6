//! The command-line entries the `icrl` binary calls: each resolves a preset
//! (or a resumed run's config) with `--set` overrides, runs the library and
//! reports; argument parsing itself stays in `src/bin`.
//! - [`pretrain`]: `icrl pretrain` for EPPO and AD.
//! - [`dataset`]: `icrl dataset`, learning histories for AD.
//! - [`sweep`]: `icrl sweep`, seeds and settings as a Slurm job array, and their table.
//! - [`in_context`]: the held-out in-context check an EPPO pretrain ends with.

pub mod dataset;
pub mod in_context;
pub mod pretrain;
pub mod sweep;
