//! A safe wrapper over `mujoco-sys`: one concept per file.
//!
//! - [`Model`] (`model.rs`): a compiled model from a file or an XML string.
//! - [`Data`] (`data.rs`): the simulation state; `step` reports [`Warnings`].
//! - [`Renderer`] (`render.rs`): off-screen frames through OSMesa, as
//!   [`RgbImage`] or PNG.
//! - `hook.rs`: the process-wide fatal-error hook ([`ensure_hooks`],
//!   [`guarded`]) that turns MuJoCo's `mju_error` into `MujocoError::Engine`
//!   instead of a wait-for-Enter-then-exit.

mod data;
mod hook;
mod model;
mod render;

pub use data::{Data, Warning, Warnings};
pub use hook::{ensure_hooks, guarded, last_warning};
pub use model::{Model, ObjType};
pub use render::{Camera, Quality, RenderError, Renderer, RgbImage};
