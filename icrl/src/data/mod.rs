//! Learning-history data for supervised pretraining:
//! - [`histories`]: the HDF5 file format (DSRL-compatible layout), read and written.
//! - [`merge`]: the shards of one dataset as one file, through HDF5 virtual datasets.
//! - [`dataset`]: making a dataset: PPO-Lagrangian (or the noisy optimal
//!   policy) run on every pretraining task and cost limit.

pub mod dataset;
pub mod histories;
pub mod merge;
