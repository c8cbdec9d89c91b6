//! Off-screen rendering through OSMesa on a scene with a red box.

use integration_tests::{RED_BOX, is_red};
use safety_envs::mujoco::{Camera, Data, Model, Quality, Renderer};

fn red_box() -> (Model, Data) {
    let model = Model::from_xml_str(RED_BOX).expect("fixture compiles");
    let mut data = Data::new(&model).expect("data");
    data.forward(&model).expect("forward");
    (model, data)
}

#[test]
fn named_camera_sees_the_red_box_at_the_centre() {
    let (model, mut data) = red_box();
    let (width, height) = (96, 64);
    let mut renderer = Renderer::new(&model, width, height).expect("renderer");
    let image = renderer
        .render(&model, &mut data, &Camera::Named("top".into()))
        .expect("render");
    assert_eq!((image.width, image.height), (width, height));
    assert_eq!(image.pixels.len(), width * height * 3);
    let centre = image.pixel(width / 2, height / 2).unwrap();
    assert!(is_red(centre), "centre pixel {centre:?} is not red");
    // The corners look at the grey floor, not at the box.
    for (x, y) in [
        (0, 0),
        (width - 1, 0),
        (0, height - 1),
        (width - 1, height - 1),
    ] {
        let px = image.pixel(x, y).unwrap();
        assert!(!is_red(px), "corner ({x}, {y}) is red: {px:?}");
    }
    assert_eq!(image.pixel(width, 0), None);
}

#[test]
fn free_top_down_camera_sees_the_box_and_png_round_trips() {
    let (model, mut data) = red_box();
    let mut renderer = Renderer::with_quality(&model, 64, 64, Quality::Fast).expect("renderer");
    let image = renderer
        .render(&model, &mut data, &Camera::top_down([0.0, 0.0], 2.0))
        .expect("render");
    assert!(is_red(image.pixel(32, 32).unwrap()));

    let path = std::env::temp_dir().join(format!("red_box_{}.png", std::process::id()));
    image.save_png(&path).expect("save png");
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
    let reader = decoder.read_info().expect("png header");
    assert_eq!((reader.info().width, reader.info().height), (64, 64));
    std::fs::remove_file(&path).ok();
}

#[test]
fn larger_than_default_offscreen_buffer_and_box_moves_in_image() {
    // MuJoCo's default off-screen buffer is 640x480: ask for more.
    let (mut model, mut data) = red_box();
    let mut renderer = Renderer::with_quality(&model, 800, 600, Quality::Fast).expect("renderer");
    let camera = Camera::top_down([0.0, 0.0], 2.0);
    let before = renderer.render(&model, &mut data, &camera).expect("render");
    assert_eq!((before.width, before.height), (800, 600));
    assert!(is_red(before.pixel(400, 300).unwrap()));

    // Move the box to +x in the compiled model: it leaves the centre and
    // appears to the right (+x is right in a top-down view).
    let geom = model.id(safety_envs::mujoco::ObjType::Geom, "red").unwrap();
    model.geom_pos_mut(geom).unwrap()[0] = 0.6;
    data.forward(&model).unwrap();
    let after = renderer.render(&model, &mut data, &camera).expect("render");
    assert!(!is_red(after.pixel(400, 300).unwrap()));
    let right = (401..800).find(|&x| is_red(after.pixel(x, 300).unwrap()));
    assert!(right.is_some(), "the moved box is not right of the centre");
}

#[test]
fn unknown_camera_is_an_error() {
    let (model, mut data) = red_box();
    let mut renderer = Renderer::with_quality(&model, 16, 16, Quality::Fast).expect("renderer");
    let err = renderer
        .render(&model, &mut data, &Camera::Named("nope".into()))
        .unwrap_err();
    assert!(err.to_string().contains("nope"), "{err}");
}

#[test]
fn zero_size_is_rejected() {
    let (model, _) = red_box();
    assert!(Renderer::new(&model, 0, 10).is_err());
}
