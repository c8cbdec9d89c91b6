//! [`Model`]: an owned, compiled MuJoCo model (`mjModel`).

use std::ffi::{CString, c_char, c_int};
use std::ops::Range;
use std::path::Path;
use std::ptr::NonNull;
use std::sync::Mutex;

use mujoco_sys as sys;

use super::hook::{ensure_hooks, guarded};
use crate::error::MujocoError;

/// Size of the buffer MuJoCo writes its load error into.
const ERROR_BUF_LEN: usize = 1000;

/// MuJoCo 2.2's XML loader keeps global state (the last parsed model, for
/// `mj_saveLastXML`), so loads are serialised.
static LOAD_LOCK: Mutex<()> = Mutex::new(());

/// The kinds of named model elements that [`Model::id`] looks up.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObjType {
    Body,
    Joint,
    Geom,
    Site,
    Camera,
    Light,
    Mesh,
    Material,
    Texture,
    Tendon,
    Actuator,
    Sensor,
}

impl std::fmt::Display for ObjType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = match self {
            ObjType::Body => "body",
            ObjType::Joint => "joint",
            ObjType::Geom => "geom",
            ObjType::Site => "site",
            ObjType::Camera => "camera",
            ObjType::Light => "light",
            ObjType::Mesh => "mesh",
            ObjType::Material => "material",
            ObjType::Texture => "texture",
            ObjType::Tendon => "tendon",
            ObjType::Actuator => "actuator",
            ObjType::Sensor => "sensor",
        };
        f.write_str(name)
    }
}

impl ObjType {
    fn raw(self) -> sys::mjtObj {
        match self {
            ObjType::Body => sys::mjtObj__mjOBJ_BODY,
            ObjType::Joint => sys::mjtObj__mjOBJ_JOINT,
            ObjType::Geom => sys::mjtObj__mjOBJ_GEOM,
            ObjType::Site => sys::mjtObj__mjOBJ_SITE,
            ObjType::Camera => sys::mjtObj__mjOBJ_CAMERA,
            ObjType::Light => sys::mjtObj__mjOBJ_LIGHT,
            ObjType::Mesh => sys::mjtObj__mjOBJ_MESH,
            ObjType::Material => sys::mjtObj__mjOBJ_MATERIAL,
            ObjType::Texture => sys::mjtObj__mjOBJ_TEXTURE,
            ObjType::Tendon => sys::mjtObj__mjOBJ_TENDON,
            ObjType::Actuator => sys::mjtObj__mjOBJ_ACTUATOR,
            ObjType::Sensor => sys::mjtObj__mjOBJ_SENSOR,
        }
    }

    /// Number of elements of this kind in `m`.
    fn count(self, m: &sys::mjModel) -> c_int {
        match self {
            ObjType::Body => m.nbody,
            ObjType::Joint => m.njnt,
            ObjType::Geom => m.ngeom,
            ObjType::Site => m.nsite,
            ObjType::Camera => m.ncam,
            ObjType::Light => m.nlight,
            ObjType::Mesh => m.nmesh,
            ObjType::Material => m.nmat,
            ObjType::Texture => m.ntex,
            ObjType::Tendon => m.ntendon,
            ObjType::Actuator => m.nu,
            ObjType::Sensor => m.nsensor,
        }
    }
}

/// A compiled MuJoCo model, owning its `mjModel`.
///
/// Environments may write positions and sizes into the compiled model through
/// [`Model::raw_mut`] or the row helpers ([`Model::body_pos_mut`], ...) without
/// recompiling; call `Data::forward` afterwards.
pub struct Model {
    ptr: NonNull<sys::mjModel>,
}

// SAFETY: a `Model` owns its `mjModel` exclusively (no other handle to it
// exists). MuJoCo only reads an `mjModel` in the simulation and rendering
// calls (they take `const mjModel*`), so sharing `&Model` between threads that
// each step their own `mjData` is safe: this is MuJoCo's documented way of
// running many simulations of one model in parallel. Mutation needs `&mut`.
unsafe impl Send for Model {}
unsafe impl Sync for Model {}

impl Model {
    /// Loads and compiles an MJCF file. A missing file gives an error naming
    /// the path; an invalid one gives MuJoCo's own message.
    pub fn from_xml_file(path: impl AsRef<Path>) -> Result<Self, MujocoError> {
        let path = path.as_ref();
        let source_name = path.display().to_string();
        if !path.is_file() {
            return Err(MujocoError::Load {
                source_name,
                message: String::from("no such file"),
            });
        }
        if let Ok(text) = std::fs::read(path) {
            preflight(&String::from_utf8_lossy(&text), &source_name)?;
        }
        let c_path = path_to_cstring(path, &source_name)?;
        load_xml(&c_path, std::ptr::null(), source_name)
    }

    /// Compiles an MJCF document held in memory (through MuJoCo's virtual file
    /// system, so nothing is written to disk). Assets the document names by
    /// relative path are looked up in the current directory.
    pub fn from_xml_str(xml: &str) -> Result<Self, MujocoError> {
        const NAME: &str = "model.xml";
        let source_name = String::from("<xml string>");
        preflight(xml, &source_name)?;
        let bytes = xml.as_bytes();
        let size = c_int::try_from(bytes.len()).map_err(|_| MujocoError::Load {
            source_name: source_name.clone(),
            message: format!("document too large ({} bytes)", bytes.len()),
        })?;
        let vfs = Vfs::new()?;
        let c_name = CString::new(NAME).expect("constant has no NUL");
        // SAFETY: `vfs` is initialised; MuJoCo copies the name and allocates
        // `size` bytes that we fill below before anything reads them.
        let status =
            guarded(|| unsafe { sys::mj_makeEmptyFileVFS(vfs.ptr, c_name.as_ptr(), size) })?;
        let index = guarded(|| unsafe { sys::mj_findFileVFS(vfs.ptr, c_name.as_ptr()) })?;
        if status != 0 || index < 0 {
            return Err(MujocoError::Load {
                source_name,
                message: format!("cannot create virtual file (status {status})"),
            });
        }
        // SAFETY: `index` is a valid slot whose buffer holds `size` bytes.
        unsafe {
            let data = (*vfs.ptr).filedata[index as usize] as *mut u8;
            std::ptr::copy_nonoverlapping(bytes.as_ptr(), data, bytes.len());
        }
        load_xml(&c_name, vfs.ptr, source_name)
    }

    /// Copies this model (`mj_copyModel`); fails only if MuJoCo cannot allocate.
    pub fn try_clone(&self) -> Result<Self, MujocoError> {
        // SAFETY: `self.ptr` is a valid model; a null destination asks MuJoCo
        // to allocate the copy.
        let raw =
            guarded(|| unsafe { sys::mj_copyModel(std::ptr::null_mut(), self.ptr.as_ptr()) })?;
        NonNull::new(raw)
            .map(|ptr| Model { ptr })
            .ok_or_else(|| MujocoError::Engine(String::from("mj_copyModel returned null")))
    }

    /// The underlying `mjModel`.
    pub fn raw(&self) -> &sys::mjModel {
        // SAFETY: `ptr` is valid for the lifetime of `self`.
        unsafe { self.ptr.as_ref() }
    }

    /// The underlying `mjModel`, mutably (to move bodies, geoms and sites of
    /// the compiled model, change colours, sizes or options).
    pub fn raw_mut(&mut self) -> &mut sys::mjModel {
        // SAFETY: `ptr` is valid and `&mut self` makes this access exclusive.
        unsafe { self.ptr.as_mut() }
    }

    /// Raw pointer for FFI calls that take `const mjModel*`.
    pub(crate) fn as_ptr(&self) -> *const sys::mjModel {
        self.ptr.as_ptr()
    }

    /// The index of the element `name` of kind `kind`.
    pub fn id(&self, kind: ObjType, name: &str) -> Result<usize, MujocoError> {
        let c_name = CString::new(name)
            .map_err(|_| MujocoError::Invalid(format!("name {name:?} contains a NUL byte")))?;
        // SAFETY: valid model and NUL-terminated name; mj_name2id only reads.
        let id = guarded(|| unsafe {
            sys::mj_name2id(self.as_ptr(), kind.raw() as c_int, c_name.as_ptr())
        })?;
        usize::try_from(id)
            .map_err(|_| MujocoError::Invalid(format!("the model has no {kind} named {name:?}")))
    }

    /// Simulation time step in seconds (`opt.timestep`).
    pub fn timestep(&self) -> f64 {
        self.raw().opt.timestep
    }

    /// Number of position coordinates.
    pub fn nq(&self) -> usize {
        self.raw().nq as usize
    }

    /// Number of degrees of freedom.
    pub fn nv(&self) -> usize {
        self.raw().nv as usize
    }

    /// Number of actuators (the length of `ctrl`).
    pub fn nu(&self) -> usize {
        self.raw().nu as usize
    }

    /// Number of bodies, the world body included.
    pub fn nbody(&self) -> usize {
        self.raw().nbody as usize
    }

    /// The slice of `sensordata` that the sensor `name` writes.
    pub fn sensor_range(&self, name: &str) -> Result<Range<usize>, MujocoError> {
        let id = self.id(ObjType::Sensor, name)?;
        let m = self.raw();
        // SAFETY: `id < nsensor` (checked by `id`), the arrays hold nsensor entries.
        let (adr, dim) = unsafe { (*m.sensor_adr.add(id), *m.sensor_dim.add(id)) };
        Ok(adr as usize..(adr + dim) as usize)
    }

    /// The control range of actuator `id`, if it is limited.
    pub fn actuator_ctrlrange(&self, id: usize) -> Result<Option<[f64; 2]>, MujocoError> {
        let m = self.raw();
        check_id(ObjType::Actuator, id, m)?;
        // SAFETY: `id < nu`; `actuator_ctrlrange` holds nu x 2 numbers.
        unsafe {
            if *m.actuator_ctrllimited.add(id) == 0 {
                return Ok(None);
            }
            Ok(Some(*(m.actuator_ctrlrange.add(2 * id) as *const [f64; 2])))
        }
    }

    /// Position of body `id` relative to its parent (`body_pos`).
    pub fn body_pos_mut(&mut self, id: usize) -> Result<&mut [f64; 3], MujocoError> {
        let m = self.raw_mut();
        check_id(ObjType::Body, id, m)?;
        // SAFETY: `id < nbody`; `body_pos` holds nbody x 3 numbers, owned by `self`.
        Ok(unsafe { &mut *(m.body_pos.add(3 * id) as *mut [f64; 3]) })
    }

    /// Orientation of body `id` relative to its parent (`body_quat`, w x y z).
    pub fn body_quat_mut(&mut self, id: usize) -> Result<&mut [f64; 4], MujocoError> {
        let m = self.raw_mut();
        check_id(ObjType::Body, id, m)?;
        // SAFETY: `id < nbody`; `body_quat` holds nbody x 4 numbers.
        Ok(unsafe { &mut *(m.body_quat.add(4 * id) as *mut [f64; 4]) })
    }

    /// Position of geom `id` in its body's frame (`geom_pos`).
    pub fn geom_pos_mut(&mut self, id: usize) -> Result<&mut [f64; 3], MujocoError> {
        let m = self.raw_mut();
        check_id(ObjType::Geom, id, m)?;
        // SAFETY: `id < ngeom`; `geom_pos` holds ngeom x 3 numbers.
        Ok(unsafe { &mut *(m.geom_pos.add(3 * id) as *mut [f64; 3]) })
    }

    /// Size parameters of geom `id` (`geom_size`; meaning depends on the type).
    pub fn geom_size_mut(&mut self, id: usize) -> Result<&mut [f64; 3], MujocoError> {
        let m = self.raw_mut();
        check_id(ObjType::Geom, id, m)?;
        // SAFETY: `id < ngeom`; `geom_size` holds ngeom x 3 numbers.
        Ok(unsafe { &mut *(m.geom_size.add(3 * id) as *mut [f64; 3]) })
    }

    /// Colour of geom `id` (`geom_rgba`).
    pub fn geom_rgba_mut(&mut self, id: usize) -> Result<&mut [f32; 4], MujocoError> {
        let m = self.raw_mut();
        check_id(ObjType::Geom, id, m)?;
        // SAFETY: `id < ngeom`; `geom_rgba` holds ngeom x 4 floats.
        Ok(unsafe { &mut *(m.geom_rgba.add(4 * id) as *mut [f32; 4]) })
    }

    /// Position of site `id` in its body's frame (`site_pos`).
    pub fn site_pos_mut(&mut self, id: usize) -> Result<&mut [f64; 3], MujocoError> {
        let m = self.raw_mut();
        check_id(ObjType::Site, id, m)?;
        // SAFETY: `id < nsite`; `site_pos` holds nsite x 3 numbers.
        Ok(unsafe { &mut *(m.site_pos.add(3 * id) as *mut [f64; 3]) })
    }
}

impl Clone for Model {
    /// Copies the model; panics only if MuJoCo cannot allocate the copy (like
    /// any Rust allocation failure). Use [`Model::try_clone`] to handle that.
    fn clone(&self) -> Self {
        match self.try_clone() {
            Ok(model) => model,
            Err(err) => panic!("cannot copy MuJoCo model: {err}"),
        }
    }
}

impl Drop for Model {
    fn drop(&mut self) {
        // SAFETY: we own the model; it is freed exactly once.
        unsafe { sys::mj_deleteModel(self.ptr.as_ptr()) };
    }
}

impl std::fmt::Debug for Model {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let m = self.raw();
        f.debug_struct("Model")
            .field("nq", &m.nq)
            .field("nv", &m.nv)
            .field("nu", &m.nu)
            .field("nbody", &m.nbody)
            .field("ngeom", &m.ngeom)
            .field("timestep", &m.opt.timestep)
            .finish()
    }
}

fn check_id(kind: ObjType, id: usize, m: &sys::mjModel) -> Result<(), MujocoError> {
    let count = kind.count(m) as usize;
    if id < count {
        Ok(())
    } else {
        Err(MujocoError::Invalid(format!(
            "{kind} id {id} out of range (the model has {count})"
        )))
    }
}

#[cfg(unix)]
fn path_to_cstring(path: &Path, source_name: &str) -> Result<CString, MujocoError> {
    use std::os::unix::ffi::OsStrExt;
    CString::new(path.as_os_str().as_bytes()).map_err(|_| MujocoError::Load {
        source_name: source_name.to_owned(),
        message: String::from("path contains a NUL byte"),
    })
}

#[cfg(not(unix))]
fn path_to_cstring(path: &Path, source_name: &str) -> Result<CString, MujocoError> {
    CString::new(path.to_string_lossy().as_bytes()).map_err(|_| MujocoError::Load {
        source_name: source_name.to_owned(),
        message: String::from("path contains a NUL byte"),
    })
}

/// Attributes whose values are names or keywords, never numbers: a body
/// may be called "inf".
const NAMING_ATTRIBUTES: [&str; 16] = [
    "name",
    "class",
    "childclass",
    "file",
    "type",
    "material",
    "texture",
    "mesh",
    "joint",
    "body",
    "site",
    "geom",
    "tendon",
    "target",
    "builtin",
    "mark",
];

/// Runs `mj_loadXML` and wraps the result, with MuJoCo's message on failure.
/// Refuses what MuJoCo 2.2's parser does not survive (found by fuzzing the
/// loader, `icrl/tests/fuzz_loaders.rs`): an integer beyond the 32-bit
/// range in any attribute (MuJoCo reads it into an `int` and overflows) and a
/// texture whose `width * height * 3` bytes overflow MuJoCo's `int` size
/// arithmetic (it then writes past its buffer).
fn preflight(xml: &str, source_name: &str) -> Result<(), MujocoError> {
    let refuse = |message: String| {
        Err(MujocoError::Load {
            source_name: source_name.to_string(),
            message,
        })
    };
    // Attribute values: the text between `="` and the next `"`.
    let mut rest = xml;
    while let Some(at) = rest.find("=\"") {
        let key = rest[..at]
            .rsplit(|c: char| c.is_whitespace() || c == '<')
            .next()
            .unwrap_or("");
        let after = &rest[at + 2..];
        let Some(end) = after.find('"') else { break };
        for token in after[..end].split_whitespace() {
            // MuJoCo reads "nan", "inf" and 1e999 into positions and sizes
            // and builds a model that cannot simulate or draw.
            if !NAMING_ATTRIBUTES.contains(&key)
                && token.parse::<f64>().is_ok_and(|v| !v.is_finite())
            {
                return refuse(format!(
                    "{key}=\"{}\" holds {token}: numbers in a model must be finite",
                    &after[..end]
                ));
            }
            let digits = token.strip_prefix(['-', '+']).unwrap_or(token);
            if !digits.is_empty()
                && digits.bytes().all(|b| b.is_ascii_digit())
                && digits.parse::<u64>().map_or(true, |v| v > i32::MAX as u64)
            {
                return refuse(format!(
                    "the number {token} is outside the 32-bit range MuJoCo reads integers into"
                ));
            }
        }
        rest = &after[end + 1..];
    }
    // Textures: width * height * 3 bytes must fit MuJoCo's int sizes.
    let mut rest = xml;
    while let Some(at) = rest.find("<texture") {
        let tag = &rest[at..];
        let tag = &tag[..tag.find('>').unwrap_or(tag.len())];
        let attr = |name: &str| -> u64 {
            tag.split_whitespace()
                .find_map(|kv| kv.strip_prefix(name)?.strip_prefix("=\""))
                .and_then(|v| v.trim_end_matches(['"', '/']).parse::<u64>().ok())
                .unwrap_or(0)
        };
        let (w, h) = (attr("width"), attr("height"));
        if w.saturating_mul(h).saturating_mul(3 * 6) > i32::MAX as u64 {
            return refuse(format!(
                "a texture of {w} x {h} texels is more than MuJoCo can size (width * height * 3 * 6 faces must stay below 2^31)"
            ));
        }
        rest = &rest[at + "<texture".len()..];
    }
    Ok(())
}

fn load_xml(
    filename: &CString,
    vfs: *const sys::mjVFS,
    source_name: String,
) -> Result<Model, MujocoError> {
    ensure_hooks();
    let mut error = [0 as c_char; ERROR_BUF_LEN];
    let raw = {
        let _lock = LOAD_LOCK
            .lock()
            .unwrap_or_else(|poison| poison.into_inner());
        // SAFETY: NUL-terminated name, null or initialised VFS, and an error
        // buffer of the size we pass.
        guarded(|| unsafe {
            sys::mj_loadXML(
                filename.as_ptr(),
                vfs,
                error.as_mut_ptr(),
                ERROR_BUF_LEN as c_int,
            )
        })
    };
    let raw = raw.map_err(|err| MujocoError::Load {
        source_name: source_name.clone(),
        message: err.to_string(),
    })?;
    match NonNull::new(raw) {
        Some(ptr) => Ok(Model { ptr }),
        None => {
            // SAFETY: MuJoCo NUL-terminates the buffer (zeroed above anyway).
            let text = unsafe { std::ffi::CStr::from_ptr(error.as_ptr()) }
                .to_string_lossy()
                .trim()
                .to_owned();
            let message = if text.is_empty() {
                String::from("mj_loadXML failed without a message")
            } else {
                text
            };
            Err(MujocoError::Load {
                source_name,
                message,
            })
        }
    }
}

/// A heap-allocated MuJoCo virtual file system (about 2 MB), freed on drop.
struct Vfs {
    ptr: *mut sys::mjVFS,
}

impl Vfs {
    fn new() -> Result<Self, MujocoError> {
        // `mjVFS` is too large for the stack; `mj_defaultVFS` initialises it.
        let boxed: Box<std::mem::MaybeUninit<sys::mjVFS>> = Box::new_uninit();
        let ptr = Box::into_raw(boxed) as *mut sys::mjVFS;
        // SAFETY: `ptr` points to writable memory of the right size.
        if let Err(err) = guarded(|| unsafe { sys::mj_defaultVFS(ptr) }) {
            // SAFETY: allocated just above with this layout, never initialised.
            drop(unsafe { Box::from_raw(ptr as *mut std::mem::MaybeUninit<sys::mjVFS>) });
            return Err(err);
        }
        Ok(Vfs { ptr })
    }
}

impl Drop for Vfs {
    fn drop(&mut self) {
        // SAFETY: initialised by `mj_defaultVFS`; `mj_deleteVFS` frees the file
        // buffers MuJoCo allocated, then we free the struct itself.
        unsafe {
            sys::mj_deleteVFS(self.ptr);
            drop(Box::from_raw(self.ptr));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOX: &str = r#"<mujoco><worldbody><body name="b" pos="0 0 1"><freejoint/>
        <geom name="g" type="box" size=".1 .1 .1"/></body></worldbody></mujoco>"#;

    #[test]
    fn loads_from_string_and_finds_names() {
        let model = Model::from_xml_str(BOX).unwrap();
        assert_eq!(model.nq(), 7);
        assert_eq!(model.id(ObjType::Body, "b").unwrap(), 1);
        assert_eq!(model.id(ObjType::Geom, "g").unwrap(), 0);
        assert!(model.id(ObjType::Body, "nope").is_err());
    }

    #[test]
    fn numbers_and_textures_mujoco_would_overflow_on_are_refused() {
        // Found by fuzzing: these crashed MuJoCo 2.2 (out-of-bounds writes).
        let texture = |w: &str| {
            format!(
                r#"<mujoco><asset><texture name="t" type="2d" builtin="checker" width="{w}" height="256"/></asset>
                <worldbody><geom size="1 1 .1" type="plane"/></worldbody></mujoco>"#
            )
        };
        let e = Model::from_xml_str(&texture("99999999999"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("99999999999 is outside the 32-bit range"), "{e}");
        let e = Model::from_xml_str(&texture("2000000"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("a texture of 2000000 x 256 texels"), "{e}");
        Model::from_xml_str(&texture("256")).unwrap();
        // Large floats and negative numbers in range are untouched.
        let big = BOX.replace("pos=\"0 0 1\"", "pos=\"-2147483647 0 1e30\"");
        Model::from_xml_str(&big).unwrap();
        // Numbers that are not finite are named; names that read as one are not numbers.
        for bad in ["nan 0 1", "0 inf 1", "0 0 1e999", "-Infinity 0 1"] {
            let xml = BOX.replace("pos=\"0 0 1\"", &format!("pos=\"{bad}\""));
            let e = Model::from_xml_str(&xml).unwrap_err().to_string();
            assert!(
                e.contains(&format!("pos=\"{bad}\"")) && e.contains("must be finite"),
                "{e}"
            );
        }
        let named = BOX.replace("name=\"b\"", "name=\"inf\"");
        Model::from_xml_str(&named).unwrap();
    }

    #[test]
    fn clone_is_independent() {
        let mut model = Model::from_xml_str(BOX).unwrap();
        let copy = model.clone();
        model.body_pos_mut(1).unwrap()[2] = 5.0;
        assert_eq!(copy.raw().nq, 7);
        let pos = unsafe { *(copy.raw().body_pos.add(3) as *const [f64; 3]) };
        assert_eq!(pos, [0.0, 0.0, 1.0]);
        assert!(model.body_pos_mut(2).is_err());
    }
}
