//! The command-line entries the `icrl` binary calls: each resolves a preset
//! (or a resumed run's config) with `--set` overrides, runs the library and
//! reports; argument parsing itself stays in `src/bin`.
//! - [`pretrain`]: `icrl pretrain` for EPPO and AD.
//! - [`dataset`]: `icrl dataset`, learning histories for AD.

pub mod dataset;
pub mod pretrain;
