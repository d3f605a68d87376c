//! The wording of errors as a user sees them: a cause's text appears once in a report of the
//! whole error chain (as the binary prints it, [`base::error::chain`]), numbers print as numbers
//! (never as a Rust type such as `DVec4(..)`), and PLY values that are not finite or outside the
//! documented bounds are refused naming the vertex and the property.

use std::error::Error;
use std::path::Path;

use base::error::chain;
use dsgs_testkit::{scratch_dir, shared_path};
use gaussian::camera::check_rigid;
use gaussian::camera_path::CameraPathError;
use gaussian::dataset::images::load_rgb;
use gaussian::dataset::{Dataset, DatasetError, LoadOptions};
use gaussian::ply::{load_ply, parse_ply, PlyErrorKind};
use gaussian::scene::{
    MAX_ABS_OPACITY_LOGIT, MAX_ABS_POSITION, MAX_LOG_SCALE, MAX_QUAT_NORM, MIN_LOG_SCALE,
    MIN_QUAT_NORM,
};
use glam::{DMat4, DVec3, DVec4};

/// The text of the innermost cause of `e` (itself when it has none).
fn root_cause(e: &(dyn Error + 'static)) -> String {
    let mut last = e;
    while let Some(c) = last.source() {
        last = c;
    }
    last.to_string()
}

fn occurrences(haystack: &str, needle: &str) -> usize {
    haystack.matches(needle).count()
}

// ---------------------------------------------------------------------------------------------
// a cause appears once

/// A JPEG whose entropy-coded data is cut short and whose tables are garbled: the decoder's
/// error has a cause of its own, which the `image` crate also repeats in its message.
#[test]
fn a_jpeg_decode_error_shows_its_cause_once() {
    let dir = scratch_dir("errors", "jpeg");
    let good = dir.join("good.jpg");
    image::RgbImage::from_fn(32, 24, |x, y| image::Rgb([x as u8 * 7, y as u8 * 9, 100]))
        .save(&good)
        .unwrap();
    let bytes = std::fs::read(&good).unwrap();
    // Garble every byte after the start-of-image marker, keeping the JPEG signature so the
    // file is decoded as a JPEG.
    let mut checked = 0;
    for cut in [bytes.len() / 3, bytes.len() / 2, 40] {
        let mut bad = bytes[..cut].to_vec();
        for b in bad.iter_mut().skip(20) {
            *b = b.wrapping_mul(31).wrapping_add(7);
        }
        let file = dir.join(format!("bad{cut}.jpg"));
        std::fs::write(&file, &bad).unwrap();
        let Err(err) = load_rgb(&file, [0.0; 3]) else {
            continue;
        };
        let DatasetError::Image { error, .. } = &err else {
            panic!("expected a decode error, got {err:?}");
        };
        // The decoder's error is part of the message and not returned as the source, so the
        // report is the message itself: a cause repeated there would show in it.
        assert!(err.source().is_none(), "{err:?}");
        let report = chain(&err);
        let cause = root_cause(error);
        println!("{report}");
        assert!(
            report.contains("bad") && report.contains(".jpg"),
            "{report}"
        );
        assert!(!cause.is_empty());
        assert_eq!(
            occurrences(&report, &cause),
            1,
            "the cause appears once: {report}"
        );
        assert_eq!(occurrences(&report, &error.to_string()), 1, "{report}");
        checked += 1;
    }
    assert!(checked > 0, "no corruption gave a decode error");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An I/O error shows its text once, after the path.
#[test]
fn an_io_error_shows_its_cause_once() {
    let dir = scratch_dir("errors", "io");
    // `transforms_train.json` is a folder, so reading it fails with an I/O error.
    std::fs::create_dir_all(dir.join("transforms_train.json")).unwrap();
    let err = Dataset::load_nerf_synthetic(&dir, "train", &LoadOptions::default()).unwrap_err();
    let DatasetError::Io { error, .. } = &err else {
        panic!("expected an I/O error, got {err:?}");
    };
    assert!(err.source().is_none(), "{err:?}");
    let report = chain(&err);
    assert!(report.contains("transforms_train.json"), "{report}");
    assert_eq!(occurrences(&report, &error.to_string()), 1, "{report}");

    // The same for a PLY file that cannot be read, also when its error kind is reported alone.
    let err = load_ply(dir.join("transforms_train.json")).unwrap_err();
    let PlyErrorKind::Io(io) = &err.kind else {
        panic!("expected an I/O error, got {err:?}");
    };
    assert!(
        err.source().is_none() && err.kind.source().is_none(),
        "{err:?}"
    );
    for report in [chain(&err), chain(&err.kind)] {
        assert_eq!(occurrences(&report, &io.to_string()), 1, "{report}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------------------------------
// numbers print as numbers

#[test]
fn matrix_and_vector_problems_print_plain_numbers() {
    let mut m = DMat4::IDENTITY;
    m.w_axis = DVec4::new(0.0, 0.0, 0.0, 2.0);
    let msg = check_rigid(&m.transpose()).unwrap_err();
    assert!(!msg.contains("DVec") && !msg.contains("DMat"), "{msg}");
    assert!(
        msg.contains("[0, 0, 0, 2]"),
        "the last row as plain numbers: {msg}"
    );

    let msg = CameraPathError::Up(DVec3::new(0.0, f64::NAN, 0.0)).to_string();
    assert!(!msg.contains("DVec"), "{msg}");
    assert!(msg.contains("[0, NaN, 0]"), "{msg}");
}

/// A COLMAP image whose pose is not finite is refused with its numbers, not a Rust type.
#[test]
fn colmap_pose_problems_print_plain_numbers() {
    let dir = scratch_dir("errors", "pose");
    let sparse = dir.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::write(sparse.join("cameras.txt"), "1 PINHOLE 8 6 10 10 4 3\n").unwrap();
    std::fs::write(sparse.join("images.txt"), "1 0 0 0 0 0 0 1 1 a.png\n\n").unwrap();
    std::fs::write(sparse.join("points3D.txt"), "").unwrap();
    let err = Dataset::load(&dir, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("images.txt") && err.contains("a.png"), "{err}");
    assert!(
        err.contains("[0, 0, 0, 0]") && !err.contains("0.0"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------------------------------
// PLY values

const PROPS: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
];

/// An ASCII PLY of five ordinary Gaussians, with `value` (text) put in `property` of vertex
/// `vertex`. `double_prop` declares that property as a `double`.
fn ply_with(vertex: usize, property: &str, value: &str, double_prop: bool) -> Vec<u8> {
    let mut text = String::from("ply\nformat ascii 1.0\nelement vertex 5\n");
    for p in PROPS {
        let ty = if double_prop && p == property {
            "double"
        } else {
            "float"
        };
        text.push_str(&format!("property {ty} {p}\n"));
    }
    text.push_str("end_header\n");
    for v in 0..5 {
        let row: Vec<String> = PROPS
            .iter()
            .map(|&p| {
                if v == vertex && p == property {
                    return value.to_string();
                }
                match p {
                    "x" | "y" | "z" => format!("{}", v as f32 * 0.5 - 1.0),
                    "opacity" => "-2".into(),
                    "scale_0" | "scale_1" | "scale_2" => "-4.5".into(),
                    "rot_0" => "1".into(),
                    "rot_1" | "rot_2" | "rot_3" => "0.1".into(),
                    _ => "0.3".into(),
                }
            })
            .collect();
        text.push_str(&row.join(" "));
        text.push('\n');
    }
    text.into_bytes()
}

/// The message for a refused PLY, checked to name the file, the vertex and the property.
fn refused(vertex: usize, property: &str, value: &str, double_prop: bool) -> String {
    let bytes = ply_with(vertex, property, value, double_prop);
    let err = match parse_ply(&bytes, Path::new("scene.ply")) {
        Ok(_) => panic!("{property} = {value} at vertex {vertex} was accepted"),
        Err(e) => e,
    };
    let m = err.to_string();
    println!("{m}");
    assert!(m.starts_with("scene.ply: "), "names the file: {m}");
    assert!(
        m.contains(&format!("vertex` instance {vertex},")),
        "names the vertex: {m}"
    );
    assert!(m.contains(property), "names the property: {m}");
    m
}

#[test]
fn ordinary_values_load() {
    let g = parse_ply(&ply_with(0, "x", "0", false), Path::new("scene.ply"))
        .unwrap()
        .gaussians;
    assert_eq!(g.len(), 5);
    // Values at the edge of each documented range are still accepted.
    for (property, value) in [
        ("x", MAX_ABS_POSITION.to_string()),
        ("z", (-MAX_ABS_POSITION).to_string()),
        ("scale_0", MAX_LOG_SCALE.to_string()),
        ("scale_2", MIN_LOG_SCALE.to_string()),
        ("opacity", MAX_ABS_OPACITY_LOGIT.to_string()),
        ("opacity", (-MAX_ABS_OPACITY_LOGIT).to_string()),
    ] {
        let bytes = ply_with(2, property, &value, false);
        assert!(
            parse_ply(&bytes, Path::new("scene.ply")).is_ok(),
            "{property} = {value} refused"
        );
    }
    // A real trained scene passes every bound.
    let trained = load_ply(shared_path("data/gaussians/trained_9080.ply")).unwrap();
    assert!(!trained.is_empty());
}

#[test]
fn a_non_finite_value_names_the_vertex_and_the_property() {
    for (property, value) in [
        ("scale_1", "nan"),
        ("x", "inf"),
        ("opacity", "-inf"),
        ("f_dc_2", "nan"),
        ("rot_2", "nan"),
    ] {
        let m = refused(3, property, value, false);
        assert!(m.contains("non-finite"), "{m}");
        assert!(
            m.to_lowercase().contains(value.trim_start_matches('-')),
            "names the value: {m}"
        );
    }
    // A double beyond the f32 range would become infinite.
    let m = refused(1, "y", "1e300", true);
    assert!(m.contains("non-finite") && m.contains("32-bit"), "{m}");
}

#[test]
fn absurd_values_are_refused_naming_the_vertex_and_the_property() {
    // A log-scale of 1e30 overflows exp; the message says so and gives the range.
    let m = refused(4, "scale_0", "1e30", false);
    assert!(
        m.contains(&MAX_LOG_SCALE.to_string()),
        "gives the bound: {m}"
    );
    for (property, value) in [
        ("scale_1", format!("{}", MAX_LOG_SCALE + 1.0)),
        ("scale_2", format!("{}", MIN_LOG_SCALE * 2.0)),
        ("x", format!("{:e}", MAX_ABS_POSITION * 10.0)),
        ("z", format!("{:e}", -MAX_ABS_POSITION * 10.0)),
        ("opacity", format!("{:e}", MAX_ABS_OPACITY_LOGIT * 10.0)),
        ("opacity", "-1e30".into()),
    ] {
        refused(0, property, &value, false);
    }
}

#[test]
fn rotations_that_cannot_be_normalised_are_refused() {
    for (rot, why) in [
        (["0", "0", "0", "0"], "zero"),
        (["1e-20", "0", "0", "0"], "below the smallest norm"),
        (["1e30", "0", "0", "1e30"], "above the largest norm"),
    ] {
        let mut text = String::from_utf8(ply_with(9, "x", "0", false)).unwrap();
        // Replace vertex 2's rotation (the last four values of its row).
        let body_start = text.find("end_header\n").unwrap() + "end_header\n".len();
        let mut rows: Vec<String> = text[body_start..].lines().map(str::to_string).collect();
        let mut cells: Vec<String> = rows[2].split(' ').map(str::to_string).collect();
        let n = cells.len();
        for (c, v) in cells[n - 4..].iter_mut().zip(rot) {
            *c = v.to_string();
        }
        rows[2] = cells.join(" ");
        text.truncate(body_start);
        text.push_str(&(rows.join("\n") + "\n"));
        let m = match parse_ply(text.as_bytes(), Path::new("scene.ply")) {
            Ok(_) => panic!("a rotation {why} was accepted"),
            Err(e) => e.to_string(),
        };
        println!("{m}");
        assert!(
            m.contains("vertex` instance 2,") && m.contains("rot_"),
            "{why}: {m}"
        );
        assert!(
            m.contains(&format!("{MIN_QUAT_NORM:e}")) && m.contains(&format!("{MAX_QUAT_NORM:e}")),
            "{why}: gives the range: {m}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// the wrong kind of file or folder is named as such

/// An image (or any file not starting with the `ply` line) given as a scene is named as not a
/// PLY file, whatever bytes it starts with.
#[test]
fn a_file_that_is_not_a_ply_is_named_so() {
    let jpeg = shared_path("data/styles/mondrian.jpg");
    let err = load_ply(&jpeg).unwrap_err().to_string();
    assert!(
        err.contains("not a PLY file") && err.contains("mondrian.jpg"),
        "{err}"
    );
    let e = parse_ply(
        b"plywood\nformat ascii 1.0\nend_header\n",
        Path::new("x.ply"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("not a PLY file"), "{e}");
}

/// A dataset folder that does not exist, or a file given as one, is named as such rather than
/// as a folder without a known layout.
#[test]
fn a_missing_dataset_folder_is_named_so() {
    let dir = scratch_dir("errors", "missing-dataset");
    let missing = dir.join("no-such-scene");
    let err = Dataset::load(&missing, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("no-such-scene") && err.contains("dataset folder not found"),
        "{err}"
    );
    let file = dir.join("scene.txt");
    std::fs::write(&file, "x").unwrap();
    let err = Dataset::load(&file, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("scene.txt") && err.contains("not a folder"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
