//! [`Data`]: the simulation state of one MuJoCo model (`mjData`), and the
//! [`Warnings`] each step reports.

use std::ptr::NonNull;

use mujoco_sys as sys;

use super::hook::{ensure_hooks, guarded};
use super::model::Model;
use crate::error::MujocoError;

/// One kind of MuJoCo warning (`mjtWarning`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Warning {
    /// Invalid inertia (mjWARN_INERTIA).
    Inertia,
    /// Contact buffer full (mjWARN_CONTACTFULL).
    ContactFull,
    /// Constraint buffer full (mjWARN_CNSTRFULL).
    CnstrFull,
    /// Visual geom buffer full (mjWARN_VGEOMFULL).
    VgeomFull,
    /// NaN or huge qpos: MuJoCo reset the state (mjWARN_BADQPOS).
    BadQpos,
    /// NaN or huge qvel: MuJoCo reset the state (mjWARN_BADQVEL).
    BadQvel,
    /// NaN or huge qacc: MuJoCo reset the state (mjWARN_BADQACC).
    BadQacc,
    /// NaN or huge ctrl: MuJoCo zeroed the controls (mjWARN_BADCTRL).
    BadCtrl,
}

impl Warning {
    /// All kinds, in `mjtWarning` order (the index into `mjData::warning`).
    pub const ALL: [Warning; 8] = [
        Warning::Inertia,
        Warning::ContactFull,
        Warning::CnstrFull,
        Warning::VgeomFull,
        Warning::BadQpos,
        Warning::BadQvel,
        Warning::BadQacc,
        Warning::BadCtrl,
    ];

    fn bit(self) -> u8 {
        1 << (self as u8)
    }
}

// The bit set below relies on the order and count of `mjtWarning`.
const _: () = assert!(sys::mjtWarning__mjNWARNING as usize == Warning::ALL.len());
const _: () = assert!(sys::mjtWarning__mjWARN_BADCTRL as usize == Warning::BadCtrl as usize);
const _: () = assert!(sys::mjtWarning__mjWARN_INERTIA as usize == Warning::Inertia as usize);

/// The set of warnings newly raised during one call (a step, a forward pass).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Warnings(u8);

impl Warnings {
    /// No warning.
    pub fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// Whether `kind` was raised.
    pub fn contains(self, kind: Warning) -> bool {
        self.0 & kind.bit() != 0
    }

    /// MuJoCo found a NaN or a huge value and reset the state (or zeroed the
    /// controls): the transition is not physical and must not be trained on.
    pub fn state_was_reset(self) -> bool {
        [
            Warning::BadQpos,
            Warning::BadQvel,
            Warning::BadQacc,
            Warning::BadCtrl,
        ]
        .iter()
        .any(|&w| self.contains(w))
    }

    /// The kinds raised, in `mjtWarning` order.
    pub fn iter(self) -> impl Iterator<Item = Warning> {
        Warning::ALL.into_iter().filter(move |&w| self.contains(w))
    }

    fn insert(&mut self, kind: Warning) {
        self.0 |= kind.bit();
    }
}

/// The model sizes an `mjData` is allocated from: two models with equal
/// `Dims` can share `Data` (a model and its clone, or one whose positions
/// were edited in place).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Dims {
    nq: i32,
    nv: i32,
    na: i32,
    nu: i32,
    nbody: i32,
    njnt: i32,
    ngeom: i32,
    nsite: i32,
    ncam: i32,
    nlight: i32,
    ntendon: i32,
    nwrap: i32,
    nmocap: i32,
    nsensordata: i32,
    nuserdata: i32,
    nm: i32,
    nd: i32,
    nconmax: i32,
    njmax: i32,
    nstack: i32,
}

impl Dims {
    fn of(m: &sys::mjModel) -> Self {
        Dims {
            nq: m.nq,
            nv: m.nv,
            na: m.na,
            nu: m.nu,
            nbody: m.nbody,
            njnt: m.njnt,
            ngeom: m.ngeom,
            nsite: m.nsite,
            ncam: m.ncam,
            nlight: m.nlight,
            ntendon: m.ntendon,
            nwrap: m.nwrap,
            nmocap: m.nmocap,
            nsensordata: m.nsensordata,
            nuserdata: m.nuserdata,
            nm: m.nM,
            nd: m.nD,
            nconmax: m.nconmax,
            njmax: m.njmax,
            nstack: m.nstack,
        }
    }
}

/// The simulation state of a model, owning its `mjData`.
///
/// Every call that runs the engine takes the model explicitly and checks that
/// it has the sizes this data was made for.
pub struct Data {
    ptr: NonNull<sys::mjData>,
    dims: Dims,
}

// SAFETY: a `Data` owns its `mjData` exclusively and MuJoCo keeps no
// thread-bound state in it, so it may move between threads. It is not `Sync`
// by choice: reads through `&Data` alias writes MuJoCo may do through `&mut`.
unsafe impl Send for Data {}

impl Data {
    /// Allocates the state for `model` and resets it to the model's defaults
    /// (`qpos0`, zero velocity, time 0).
    pub fn new(model: &Model) -> Result<Self, MujocoError> {
        ensure_hooks();
        // SAFETY: `model` is a valid compiled model.
        let raw = guarded(|| unsafe { sys::mj_makeData(model.as_ptr()) })?;
        let ptr = NonNull::new(raw)
            .ok_or_else(|| MujocoError::Engine(String::from("mj_makeData returned null")))?;
        Ok(Data {
            ptr,
            dims: Dims::of(model.raw()),
        })
    }

    pub(crate) fn check(&self, model: &Model) -> Result<(), MujocoError> {
        let dims = Dims::of(model.raw());
        if dims == self.dims {
            Ok(())
        } else {
            Err(MujocoError::Invalid(format!(
                "this Data was made for a model of sizes {:?}, not {:?}",
                self.dims, dims
            )))
        }
    }

    /// Runs `f` under the error hook; on an engine error, resets the data so
    /// it is usable again, then returns the error.
    fn run(
        &mut self,
        model: &Model,
        f: impl FnOnce(*const sys::mjModel, *mut sys::mjData),
    ) -> Result<Warnings, MujocoError> {
        self.check(model)?;
        // MuJoCo's automatic reset on a bad state (`mj_resetData` inside
        // `mj_step`) zeroes every counter and then counts only the warning
        // that caused it, so a before/after difference can miss a repeat.
        // Instead, start the call from zero, read what it raised, and add the
        // previous totals back.
        let before = self.warning_counts();
        self.set_warning_counts(&[0; 8]);
        let (m, d) = (model.as_ptr(), self.ptr.as_ptr());
        match guarded(|| f(m, d)) {
            Ok(()) => {
                let raised = self.warning_counts();
                let totals: [i32; 8] =
                    std::array::from_fn(|i| before[i].saturating_add(raised[i].max(0)));
                self.set_warning_counts(&totals);
                let mut set = Warnings::default();
                for (kind, &n) in Warning::ALL.into_iter().zip(&raised) {
                    if n > 0 {
                        set.insert(kind);
                    }
                }
                Ok(set)
            }
            Err(err) => {
                // SAFETY: an engine error leaves `d` in an unspecified state;
                // `mj_resetData` rebuilds it from the (unchanged) model.
                let _ = guarded(|| unsafe { sys::mj_resetData(m, d) });
                Err(err)
            }
        }
    }

    /// Advances the simulation by one time step (`mj_step`) and reports the
    /// warnings raised during it. On an engine error the data is reset.
    pub fn step(&mut self, model: &Model) -> Result<Warnings, MujocoError> {
        // SAFETY: `m` and `d` are valid and of matching sizes (checked in run).
        self.run(model, |m, d| unsafe { sys::mj_step(m, d) })
    }

    /// Computes positions, velocities and derived quantities without
    /// advancing time (`mj_forward`), e.g. after writing `qpos`.
    pub fn forward(&mut self, model: &Model) -> Result<Warnings, MujocoError> {
        // SAFETY: as in `step`.
        self.run(model, |m, d| unsafe { sys::mj_forward(m, d) })
    }

    /// Resets the state to the model's defaults (`mj_resetData`) and clears
    /// the warning counters.
    pub fn reset(&mut self, model: &Model) -> Result<(), MujocoError> {
        self.check(model)?;
        let (m, d) = (model.as_ptr(), self.ptr.as_ptr());
        // SAFETY: valid pointers of matching sizes.
        guarded(|| unsafe { sys::mj_resetData(m, d) })
    }

    /// How often each kind of warning was raised since the last reset, in
    /// `mjtWarning` order (`warning[i].number`).
    pub fn warning_counts(&self) -> [i32; 8] {
        let w = &self.raw().warning;
        std::array::from_fn(|i| w[i].number)
    }

    fn set_warning_counts(&mut self, counts: &[i32; 8]) {
        for (stat, &n) in self.raw_mut().warning.iter_mut().zip(counts) {
            stat.number = n;
        }
    }

    /// The underlying `mjData`.
    pub fn raw(&self) -> &sys::mjData {
        // SAFETY: valid for the lifetime of `self`.
        unsafe { self.ptr.as_ref() }
    }

    /// The underlying `mjData`, mutably.
    pub fn raw_mut(&mut self) -> &mut sys::mjData {
        // SAFETY: valid, and `&mut self` makes the access exclusive.
        unsafe { self.ptr.as_mut() }
    }

    /// Raw pointer for FFI calls (the renderer).
    pub(crate) fn as_mut_ptr(&mut self) -> *mut sys::mjData {
        self.ptr.as_ptr()
    }

    /// Simulation time in seconds.
    pub fn time(&self) -> f64 {
        self.raw().time
    }

    /// Sets the simulation time.
    pub fn set_time(&mut self, time: f64) {
        self.raw_mut().time = time;
    }

    /// Number of active contacts after the last step or forward pass.
    pub fn ncon(&self) -> usize {
        self.raw().ncon.max(0) as usize
    }

    /// The active contacts.
    pub fn contacts(&self) -> &[sys::mjContact] {
        // SAFETY: `contact` holds nconmax entries, of which the first ncon are live.
        unsafe { slice(self.raw().contact, self.ncon()) }
    }
}

/// A shared slice over `len` values at `ptr` (empty when `len == 0`, where
/// MuJoCo may leave the pointer null).
///
/// SAFETY: when `len > 0`, `ptr` must point to `len` initialised values that
/// live as long as the returned borrow and are not mutated meanwhile.
unsafe fn slice<'a, T>(ptr: *const T, len: usize) -> &'a [T] {
    if len == 0 || ptr.is_null() {
        &[]
    } else {
        unsafe { std::slice::from_raw_parts(ptr, len) }
    }
}

/// The mutable counterpart of [`slice`]; same contract, plus exclusivity.
unsafe fn slice_mut<'a, T>(ptr: *mut T, len: usize) -> &'a mut [T] {
    if len == 0 || ptr.is_null() {
        &mut []
    } else {
        unsafe { std::slice::from_raw_parts_mut(ptr, len) }
    }
}

/// Read accessors for `mjData` arrays: `$name()` returns `$rows x $width`
/// numbers, the length taken from the model sizes.
macro_rules! read_arrays {
    ($($(#[$doc:meta])* $name:ident: $rows:ident x $width:literal;)*) => {
        impl Data {
            $(
                $(#[$doc])*
                pub fn $name(&self) -> &[f64] {
                    let len = self.dims.$rows.max(0) as usize * $width;
                    // SAFETY: MuJoCo allocated `$rows x $width` numbers for this array.
                    unsafe { slice(self.raw().$name, len) }
                }
            )*
        }
    };
}

/// Write accessors: `$name_mut()` for the arrays a caller may set.
macro_rules! write_arrays {
    ($($(#[$doc:meta])* $name:ident / $name_mut:ident: $rows:ident x $width:literal;)*) => {
        impl Data {
            $(
                $(#[$doc])*
                pub fn $name_mut(&mut self) -> &mut [f64] {
                    let len = self.dims.$rows.max(0) as usize * $width;
                    // SAFETY: as for reads, and `&mut self` makes the access exclusive.
                    unsafe { slice_mut(self.raw_mut().$name, len) }
                }
            )*
        }
    };
}

read_arrays! {
    /// Joint positions (nq).
    qpos: nq x 1;
    /// Joint velocities (nv).
    qvel: nv x 1;
    /// Joint accelerations from the last step (nv).
    qacc: nv x 1;
    /// Actuator activations (na).
    act: na x 1;
    /// Actuator controls (nu).
    ctrl: nu x 1;
    /// Applied generalised forces (nv).
    qfrc_applied: nv x 1;
    /// Mocap body positions (nmocap x 3).
    mocap_pos: nmocap x 3;
    /// Mocap body orientations, w x y z (nmocap x 4).
    mocap_quat: nmocap x 4;
    /// Body positions in the world frame (nbody x 3).
    xpos: nbody x 3;
    /// Body orientations as quaternions, w x y z (nbody x 4).
    xquat: nbody x 4;
    /// Body orientations as row-major rotation matrices (nbody x 9).
    xmat: nbody x 9;
    /// Geom positions in the world frame (ngeom x 3).
    geom_xpos: ngeom x 3;
    /// Geom orientations as row-major rotation matrices (ngeom x 9).
    geom_xmat: ngeom x 9;
    /// Site positions in the world frame (nsite x 3).
    site_xpos: nsite x 3;
    /// Site orientations as row-major rotation matrices (nsite x 9).
    site_xmat: nsite x 9;
    /// Sensor readings (nsensordata).
    sensordata: nsensordata x 1;
}

write_arrays! {
    /// Joint positions (nq), to set a state; call `forward` afterwards.
    qpos / qpos_mut: nq x 1;
    /// Joint velocities (nv).
    qvel / qvel_mut: nv x 1;
    /// Actuator activations (na).
    act / act_mut: na x 1;
    /// Actuator controls (nu), read by the next `step`.
    ctrl / ctrl_mut: nu x 1;
    /// Applied generalised forces (nv).
    qfrc_applied / qfrc_applied_mut: nv x 1;
    /// Mocap body positions (nmocap x 3).
    mocap_pos / mocap_pos_mut: nmocap x 3;
    /// Mocap body orientations, w x y z (nmocap x 4).
    mocap_quat / mocap_quat_mut: nmocap x 4;
}

impl Drop for Data {
    fn drop(&mut self) {
        // SAFETY: we own the data; it is freed exactly once.
        unsafe { sys::mj_deleteData(self.ptr.as_ptr()) };
    }
}

impl std::fmt::Debug for Data {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Data")
            .field("time", &self.time())
            .field("qpos", &self.qpos())
            .field("qvel", &self.qvel())
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SLIDER: &str = r#"<mujoco><worldbody><body name="b"><joint name="x" type="slide" axis="1 0 0"/>
        <geom type="sphere" size=".1" mass="1"/></body></worldbody>
        <actuator><motor joint="x" gear="1"/></actuator></mujoco>"#;

    #[test]
    fn step_advances_time_and_moves_under_control() {
        let model = Model::from_xml_str(SLIDER).unwrap();
        let mut data = Data::new(&model).unwrap();
        data.ctrl_mut()[0] = 1.0;
        for _ in 0..100 {
            assert!(data.step(&model).unwrap().is_empty());
        }
        assert!((data.time() - 100.0 * model.timestep()).abs() < 1e-9);
        assert!(data.qpos()[0] > 0.0);
        data.reset(&model).unwrap();
        assert_eq!(data.qpos(), &[0.0]);
    }

    #[test]
    fn nan_control_is_reported() {
        let model = Model::from_xml_str(SLIDER).unwrap();
        let mut data = Data::new(&model).unwrap();
        data.ctrl_mut()[0] = f64::NAN;
        let warnings = data.step(&model).unwrap();
        assert!(warnings.contains(Warning::BadCtrl), "{warnings:?}");
        assert!(warnings.state_was_reset());
        // A clean step reports nothing new; the totals keep counting.
        data.ctrl_mut()[0] = 0.0;
        assert!(data.step(&model).unwrap().is_empty());
        assert_eq!(data.warning_counts()[Warning::BadCtrl as usize], 1);
    }

    #[test]
    fn repeated_nan_state_resets_are_each_reported() {
        let model = Model::from_xml_str(SLIDER).unwrap();
        let mut data = Data::new(&model).unwrap();
        for _ in 0..3 {
            data.step(&model).unwrap();
            data.qvel_mut()[0] = f64::NAN;
            let warnings = data.step(&model).unwrap();
            assert!(warnings.contains(Warning::BadQvel), "{warnings:?}");
            assert!(data.qvel()[0].is_finite());
        }
    }

    #[test]
    fn data_of_another_model_is_rejected() {
        let model = Model::from_xml_str(SLIDER).unwrap();
        let other = Model::from_xml_str("<mujoco/>").unwrap();
        let mut data = Data::new(&model).unwrap();
        assert!(matches!(data.step(&other), Err(MujocoError::Invalid(_))));
        assert!(data.step(&model.clone()).is_ok());
    }
}

#[cfg(test)]
mod engine_error_tests {
    use super::*;

    /// Compiles (no contact at the start) but overflows the stack once the
    /// falling boxes touch the floor and the solver needs room.
    const SMALL_STACK: &str = r#"<mujoco><size nstack="300"/><worldbody>
        <geom type="plane" size="1 1 .1"/>
        <body pos="0 0 .2"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
        <body pos=".05 0 .45"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
        </worldbody></mujoco>"#;

    #[test]
    fn stack_overflow_is_an_error_and_data_is_reset() {
        let model = Model::from_xml_str(SMALL_STACK).unwrap();
        let mut data = Data::new(&model).unwrap();
        let err = (0..1000)
            .find_map(|_| data.step(&model).err())
            .expect("the small stack overflows within 1000 steps");
        assert!(matches!(&err, MujocoError::Engine(msg) if msg.contains("Stack overflow")));
        // The data was reset and steps again.
        assert_eq!(data.time(), 0.0);
        assert!(data.step(&model).is_ok());
    }
}
