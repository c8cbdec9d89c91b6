//! Integration tests live in `tests/`; this library only holds shared scene
//! fixtures: tiny MJCF scenes written for one test each.

/// A box in zero gravity with a free joint, yawed 30 degrees, driven by one
/// thrust actuator: a motor on a site with its gear along the site's x axis
/// (the body's heading), like Safety Gym's point robot.
pub const THRUSTER: &str = r#"
<mujoco model="thruster">
  <option gravity="0 0 0" timestep="0.002"/>
  <worldbody>
    <body name="robot" pos="0 0 0.5" euler="0 0 30">
      <freejoint/>
      <geom type="box" size="0.1 0.05 0.05" mass="1"/>
      <site name="thrust" pos="0 0 0"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="forward" site="thrust" gear="1 0 0 0 0 0" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"#;

/// Heading of [`THRUSTER`]'s body in degrees (its `euler` z angle).
pub const THRUSTER_YAW_DEG: f64 = 30.0;

/// A sphere on a slide joint along x, driven by a motor: the simplest model
/// with a control, used for stepping and the NaN-control warning.
pub const SLIDER: &str = r#"
<mujoco model="slider">
  <worldbody>
    <body name="ball">
      <joint name="x" type="slide" axis="1 0 0"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="x" gear="1"/>
  </actuator>
  <sensor>
    <jointpos name="x_pos" joint="x"/>
  </sensor>
</mujoco>
"#;

/// Not valid MJCF: an attribute MuJoCo's schema does not know.
pub const BOGUS_ATTRIBUTE: &str = r#"
<mujoco>
  <worldbody>
    <geom type="sphere" size="0.1" bogus_attr="1"/>
  </worldbody>
</mujoco>
"#;

/// Compiles (no contact at the initial state) but with a stack so small that
/// the constraint solver overflows it once the falling boxes touch the floor:
/// MuJoCo then calls `mju_error("Stack overflow")`, a fatal engine error.
pub const SMALL_STACK: &str = r#"
<mujoco model="small_stack">
  <size nstack="300"/>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <body pos="0 0 0.2"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
    <body pos="0.05 0 0.45"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
  </worldbody>
</mujoco>
"#;

/// A red box at the origin on a grey floor, lit from above, with a camera
/// named `top` looking straight down at it: the box fills the image centre.
pub const RED_BOX: &str = r#"
<mujoco model="red_box">
  <visual><quality offsamples="0"/></visual>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="2 2 0.1" rgba="0.5 0.5 0.5 1"/>
    <geom name="red" type="box" pos="0 0 0.1" size="0.3 0.3 0.1" rgba="1 0 0 1"/>
    <camera name="top" pos="0 0 2" xyaxes="1 0 0 0 1 0"/>
  </worldbody>
</mujoco>
"#;

/// Whether a pixel reads as red: the red channel well above green and blue.
pub fn is_red(rgb: [u8; 3]) -> bool {
    let [r, g, b] = rgb;
    r > 100 && r as u32 > 2 * g as u32 && r as u32 > 2 * b as u32
}
