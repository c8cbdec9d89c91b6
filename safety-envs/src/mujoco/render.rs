//! [`Renderer`]: off-screen rendering of a model through OSMesa (software
//! OpenGL), so frames can be made on a machine with no display and no GPU.
//!
//! Costs measured on this 2-core machine (llvmpipe, debug-profile test
//! binary with optimised dependencies): creating a renderer 50-80 ms; one
//! frame at 480x480 about 41 ms at the model's quality (shadows, 4x MSAA),
//! 2.1 ms with [`Quality::Fast`]; 64x64 fast 0.18 ms.
//!
//! Never load libEGL into a process that renders through this module: MuJoCo's
//! GL loader looks for `eglGetProcAddress` first and then fails with
//! `gladLoadGL error` (SPEC section 7).

use std::ffi::{c_int, c_uchar, c_void};
use std::io::BufWriter;
use std::marker::PhantomData;
use std::path::Path;

use mujoco_sys as sys;
use thiserror::Error;

use super::data::Data;
use super::hook::{ensure_hooks, guarded};
use super::model::{Model, ObjType};
use crate::error::MujocoError;

/// The few OSMesa entry points the renderer needs (`GL/osmesa.h`).
mod osmesa {
    use std::ffi::{c_int, c_uchar, c_uint, c_void};

    pub type Context = *mut c_void;
    /// `OSMESA_RGBA` (= `GL_RGBA`).
    pub const RGBA: c_uint = 0x1908;
    /// `GL_UNSIGNED_BYTE`.
    pub const UNSIGNED_BYTE: c_uint = 0x1401;

    #[link(name = "OSMesa")]
    unsafe extern "C" {
        pub fn OSMesaCreateContextExt(
            format: c_uint,
            depth_bits: c_int,
            stencil_bits: c_int,
            accum_bits: c_int,
            sharelist: Context,
        ) -> Context;
        pub fn OSMesaMakeCurrent(
            ctx: Context,
            buffer: *mut c_void,
            type_: c_uint,
            width: c_int,
            height: c_int,
        ) -> c_uchar;
        pub fn OSMesaDestroyContext(ctx: Context);
    }
}

/// An error while setting up rendering, rendering, or writing an image.
#[derive(Debug, Error)]
pub enum RenderError {
    #[error(transparent)]
    Mujoco(#[from] MujocoError),
    /// OSMesa or MuJoCo's GL context could not be set up.
    #[error("off-screen OpenGL (OSMesa): {0}")]
    Context(String),
    /// A size that cannot be rendered.
    #[error("invalid image size {width}x{height}: {reason}")]
    Size {
        width: usize,
        height: usize,
        reason: String,
    },
    #[error("cannot write PNG {path}: {source}")]
    Png {
        path: String,
        source: png::EncodingError,
    },
    #[error("cannot create {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// Where to look from.
#[derive(Clone, Debug, PartialEq)]
pub enum Camera {
    /// A camera defined in the model (`<camera name=...>`).
    Named(String),
    /// A free camera orbiting `lookat`: angles in degrees, MuJoCo's convention
    /// (azimuth 0 looks along +x; elevation -90 looks straight down).
    Free {
        lookat: [f64; 3],
        distance: f64,
        azimuth: f64,
        elevation: f64,
    },
    /// MuJoCo's default free camera for the model (`mjv_defaultFreeCamera`:
    /// the model's centre and extent, the angles of `<visual><global>`).
    ModelDefault,
}

impl Camera {
    /// Looks straight down at `center` from `distance`, with +x to the right
    /// and +y up in the image.
    pub fn top_down(center: [f64; 2], distance: f64) -> Self {
        Camera::Free {
            lookat: [center[0], center[1], 0.0],
            distance,
            azimuth: 90.0,
            elevation: -90.0,
        }
    }

    fn to_mjv(&self, model: &Model) -> Result<sys::mjvCamera, MujocoError> {
        let mut cam = sys::mjvCamera::default();
        match self {
            Camera::Named(name) => {
                cam.type_ = sys::mjtCamera__mjCAMERA_FIXED as c_int;
                cam.fixedcamid = model.id(ObjType::Camera, name)? as c_int;
            }
            Camera::Free {
                lookat,
                distance,
                azimuth,
                elevation,
            } => {
                cam.type_ = sys::mjtCamera__mjCAMERA_FREE as c_int;
                cam.fixedcamid = -1;
                cam.trackbodyid = -1;
                cam.lookat = *lookat;
                cam.distance = *distance;
                cam.azimuth = *azimuth;
                cam.elevation = *elevation;
            }
            Camera::ModelDefault => {
                // SAFETY: valid model; `cam` is a plain struct MuJoCo fills.
                guarded(|| unsafe { sys::mjv_defaultFreeCamera(model.as_ptr(), &mut cam) })?;
            }
        }
        Ok(cam)
    }
}

/// An 8-bit RGB image, rows from top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    /// `height` rows of `width` pixels of 3 bytes, top row first.
    pub pixels: Vec<u8>,
}

impl RgbImage {
    /// The colour at column `x`, row `y` (0 = top), or `None` outside.
    pub fn pixel(&self, x: usize, y: usize) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = 3 * (y * self.width + x);
        Some([self.pixels[i], self.pixels[i + 1], self.pixels[i + 2]])
    }

    /// Writes the image as an 8-bit RGB PNG.
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<(), RenderError> {
        let path = path.as_ref();
        let name = path.display().to_string();
        let file = std::fs::File::create(path).map_err(|source| RenderError::Io {
            path: name.clone(),
            source,
        })?;
        let png_err = |source| RenderError::Png {
            path: name.clone(),
            source,
        };
        let mut encoder =
            png::Encoder::new(BufWriter::new(file), self.width as u32, self.height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(png_err)?;
        writer.write_image_data(&self.pixels).map_err(png_err)?;
        writer.finish().map_err(png_err)
    }
}

/// How much rendering work each frame does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Quality {
    /// The model's own settings: shadows, reflections, its MSAA samples.
    #[default]
    Model,
    /// No shadows, reflections or MSAA: several times faster on llvmpipe.
    Fast,
}

/// Largest number of geoms one frame can draw.
const MAX_GEOM: c_int = 10_000;

/// An off-screen renderer of a fixed image size, bound to the thread that
/// made it: an OpenGL context is current on one thread only, so `Renderer` is
/// neither `Send` nor `Sync` (make one per thread).
pub struct Renderer {
    width: usize,
    height: usize,
    ctx: osmesa::Context,
    /// OSMesa's default framebuffer (RGBA); MuJoCo draws into its own
    /// off-screen buffer, but OSMesa needs one bound to make the context current.
    _buffer: Vec<u8>,
    buffer_ptr: *mut c_void,
    scene: Box<sys::mjvScene>,
    context: Box<sys::mjrContext>,
    option: sys::mjvOption,
    perturb: sys::mjvPerturb,
    /// `*const ()` keeps the type `!Send` and `!Sync`.
    _thread_bound: PhantomData<*const ()>,
}

impl Renderer {
    /// A renderer of `width x height` images of `model`, at the model's quality.
    pub fn new(model: &Model, width: usize, height: usize) -> Result<Self, RenderError> {
        Self::with_quality(model, width, height, Quality::Model)
    }

    /// A renderer with a chosen [`Quality`].
    pub fn with_quality(
        model: &Model,
        width: usize,
        height: usize,
        quality: Quality,
    ) -> Result<Self, RenderError> {
        ensure_hooks();
        let size_err = |reason: &str| RenderError::Size {
            width,
            height,
            reason: reason.to_owned(),
        };
        if width == 0 || height == 0 {
            return Err(size_err("both sides must be positive"));
        }
        if width > 8192 || height > 8192 {
            return Err(size_err("at most 8192 pixels a side"));
        }
        let (w, h) = (width as c_int, height as c_int);

        // SAFETY: plain FFI; a null sharelist asks for an unshared context.
        let ctx =
            unsafe { osmesa::OSMesaCreateContextExt(osmesa::RGBA, 24, 8, 0, std::ptr::null_mut()) };
        if ctx.is_null() {
            return Err(RenderError::Context(String::from(
                "OSMesaCreateContextExt failed",
            )));
        }
        let mut buffer = vec![0u8; width * height * 4];
        let buffer_ptr = buffer.as_mut_ptr() as *mut c_void;
        // From here on `renderer`'s Drop frees whatever was made.
        let mut renderer = Renderer {
            width,
            height,
            ctx,
            _buffer: buffer,
            buffer_ptr,
            scene: Box::default(),
            context: Box::default(),
            option: sys::mjvOption::default(),
            perturb: sys::mjvPerturb::default(),
            _thread_bound: PhantomData,
        };
        renderer.make_current()?;

        // MuJoCo sizes its off-screen buffer from the model: use a copy whose
        // buffer is at least the requested size.
        let mut sized = model.try_clone()?;
        {
            let vis = &mut sized.raw_mut().vis;
            vis.global.offwidth = vis.global.offwidth.max(w);
            vis.global.offheight = vis.global.offheight.max(h);
            if quality == Quality::Fast {
                vis.quality.offsamples = 0;
            }
        }
        let r = &mut renderer;
        // SAFETY: the GL context is current on this thread; the structs are
        // owned by `renderer`, initialised by MuJoCo's default functions
        // before use, and freed in Drop (free on a default struct is a no-op).
        guarded(|| unsafe {
            sys::mjv_defaultOption(&mut r.option);
            sys::mjv_defaultPerturb(&mut r.perturb);
            sys::mjv_defaultScene(&mut *r.scene);
            sys::mjr_defaultContext(&mut *r.context);
            sys::mjv_makeScene(sized.as_ptr(), &mut *r.scene, MAX_GEOM);
            sys::mjr_makeContext(
                sized.as_ptr(),
                &mut *r.context,
                sys::mjtFontScale__mjFONTSCALE_100 as c_int,
            );
            sys::mjr_setBuffer(
                sys::mjtFramebuffer__mjFB_OFFSCREEN as c_int,
                &mut *r.context,
            );
        })
        .map_err(|err| RenderError::Context(err.to_string()))?;
        if r.context.currentBuffer != sys::mjtFramebuffer__mjFB_OFFSCREEN as c_int {
            return Err(RenderError::Context(String::from(
                "MuJoCo could not select its off-screen framebuffer",
            )));
        }
        if r.context.offWidth < w || r.context.offHeight < h {
            return Err(RenderError::Context(format!(
                "off-screen buffer is {}x{}, smaller than the requested {width}x{height}",
                r.context.offWidth, r.context.offHeight
            )));
        }
        if quality == Quality::Fast {
            r.set_flag(sys::mjtRndFlag__mjRND_SHADOW, false);
            r.set_flag(sys::mjtRndFlag__mjRND_REFLECTION, false);
        }
        Ok(renderer)
    }

    /// Image width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Turns shadows on or off.
    pub fn set_shadows(&mut self, on: bool) {
        self.set_flag(sys::mjtRndFlag__mjRND_SHADOW, on);
    }

    fn set_flag(&mut self, flag: sys::mjtRndFlag, on: bool) {
        self.scene.flags[flag as usize] = on as c_uchar;
    }

    fn make_current(&mut self) -> Result<(), RenderError> {
        // SAFETY: `ctx` is live and `buffer_ptr` points to width x height
        // RGBA bytes owned by `self`.
        let ok = unsafe {
            osmesa::OSMesaMakeCurrent(
                self.ctx,
                self.buffer_ptr,
                osmesa::UNSIGNED_BYTE,
                self.width as c_int,
                self.height as c_int,
            )
        };
        if ok == 0 {
            return Err(RenderError::Context(String::from(
                "OSMesaMakeCurrent failed",
            )));
        }
        Ok(())
    }

    /// Renders the current state of `data` from `camera`. `data` is taken
    /// mutably because MuJoCo's scene update writes camera and light poses
    /// into it; the simulation state is not changed.
    pub fn render(
        &mut self,
        model: &Model,
        data: &mut Data,
        camera: &Camera,
    ) -> Result<RgbImage, RenderError> {
        data.check(model)?;
        let mut cam = camera.to_mjv(model)?;
        self.make_current()?;
        let viewport = sys::mjrRect {
            left: 0,
            bottom: 0,
            width: self.width as c_int,
            height: self.height as c_int,
        };
        let mut rgb = vec![0u8; self.width * self.height * 3];
        let (m, d) = (model.as_ptr(), data.as_mut_ptr());
        let r = &mut *self;
        // SAFETY: the context is current; model and data match (checked);
        // `rgb` holds width x height x 3 bytes, the viewport's size.
        guarded(|| unsafe {
            sys::mjr_setBuffer(
                sys::mjtFramebuffer__mjFB_OFFSCREEN as c_int,
                &mut *r.context,
            );
            sys::mjv_updateScene(
                m,
                d,
                &r.option,
                &r.perturb,
                &mut cam,
                sys::mjtCatBit__mjCAT_ALL as c_int,
                &mut *r.scene,
            );
            sys::mjr_render(viewport, &mut *r.scene, &*r.context);
            sys::mjr_readPixels(
                rgb.as_mut_ptr(),
                std::ptr::null_mut(),
                viewport,
                &*r.context,
            );
        })?;
        // OpenGL's rows run bottom to top: flip them.
        let row = self.width * 3;
        let pixels = rgb.chunks_exact(row).rev().flatten().copied().collect();
        Ok(RgbImage {
            width: self.width,
            height: self.height,
            pixels,
        })
    }
}

impl Drop for Renderer {
    fn drop(&mut self) {
        // The GL objects belong to our context: make it current to free them.
        let current = self.make_current().is_ok();
        // SAFETY: each struct was initialised by its default function (free is
        // a no-op on a default struct) and is freed once; the OSMesa context
        // is destroyed last.
        unsafe {
            let _ = guarded(|| {
                if current {
                    sys::mjr_freeContext(&mut *self.context);
                }
                sys::mjv_freeScene(&mut *self.scene);
            });
            osmesa::OSMesaDestroyContext(self.ctx);
        }
    }
}
