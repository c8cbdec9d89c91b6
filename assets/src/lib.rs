//! MJCF models of the robots and arenas used by `safety-envs`, embedded at
//! compile time so binaries do not depend on the working directory.
//!
//! - [`POINT_XML`], [`CAR_XML`]: the robots (SPEC section 6), each a complete
//!   `<mujoco>` file with its own timestep, actuators and sensors.
//! - [`ARENA_XML`]: floor, lights, top-down camera `top`, the goal site `goal`
//!   and [`MAX_HAZARDS`] hazard sites `hazard0..`.
//! - [`point_in_arena`], [`car_in_arena`]: robot and arena in one model.

/// The Point robot.
pub const POINT_XML: &str = include_str!("../xml/point.xml");
/// The Car robot.
pub const CAR_XML: &str = include_str!("../xml/car.xml");
/// The goal arena shared by both robots.
pub const ARENA_XML: &str = include_str!("../xml/arena.xml");
/// Hazard sites in [`ARENA_XML`], named `hazard0` to `hazard23`.
pub const MAX_HAZARDS: usize = 24;

/// The body of a `<mujoco ...>` document: what lies between the opening tag
/// and `</mujoco>`. Both are present in the embedded files (checked by a test).
fn inner(xml: &str) -> &str {
    let start = xml
        .find("<mujoco")
        .and_then(|i| xml[i..].find('>').map(|j| i + j + 1))
        .unwrap_or(0);
    let end = xml.rfind("</mujoco>").unwrap_or(xml.len());
    &xml[start..end]
}

/// `robot` with the arena's sections appended inside its `<mujoco>` element
/// (MJCF merges repeated sections such as `<worldbody>`).
pub fn in_arena(robot: &str) -> String {
    let body_end = robot.rfind("</mujoco>").unwrap_or(robot.len());
    format!("{}{}</mujoco>\n", &robot[..body_end], inner(ARENA_XML))
}

/// Point robot in the goal arena.
pub fn point_in_arena() -> String {
    in_arena(POINT_XML)
}

/// Car robot in the goal arena.
pub fn car_in_arena() -> String {
    in_arena(CAR_XML)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_are_whole_documents_with_all_hazards() {
        for xml in [POINT_XML, CAR_XML, ARENA_XML] {
            assert!(xml.contains("<mujoco") && xml.contains("</mujoco>"));
        }
        for i in 0..MAX_HAZARDS {
            assert!(ARENA_XML.contains(&format!("name=\"hazard{i}\"")));
        }
        assert!(!ARENA_XML.contains(&format!("name=\"hazard{MAX_HAZARDS}\"")));
        let p = point_in_arena();
        assert_eq!(p.matches("<mujoco").count(), 1);
        assert!(p.contains("name=\"goal\"") && p.contains("name=\"thrust\""));
    }
}
