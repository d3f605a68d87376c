//! Camera resizing and field of view.

use gaussian::{Camera, Intrinsics};
use glam::{DMat3, DVec3};

fn intr() -> Intrinsics {
    Intrinsics {
        fx: 1000.0,
        fy: 1010.0,
        cx: 360.0,
        cy: 640.0,
        width: 720,
        height: 1280,
    }
}

#[test]
fn fov_of_a_known_camera() {
    let k = Intrinsics {
        fx: 50.0,
        fy: 25.0,
        cx: 50.0,
        cy: 25.0,
        width: 100,
        height: 50,
    };
    // tan(fov / 2) = (W / 2) / fx = 1 and (H / 2) / fy = 1.
    assert!((k.fov_x() - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
    assert!((k.fov_y() - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
}

#[test]
fn resizing_scales_intrinsics_with_the_image() {
    let k = intr();
    let r = k.scaled(0.125);
    assert_eq!((r.width, r.height), (90, 160));
    assert_eq!((r.fx, r.fy, r.cx, r.cy), (125.0, 126.25, 45.0, 80.0));
    assert!((r.fov_x() - k.fov_x()).abs() < 1e-15);
    let r = k.resized(360, 320);
    assert_eq!((r.fx, r.fy, r.cx, r.cy), (500.0, 252.5, 180.0, 160.0));
}

/// A world point seen by the full-size camera at pixel coordinate u is seen by the scaled
/// camera at u * s: image edges (0 and W) map to edges, pixel centres i + 0.5 of the small
/// image cover the same footprint as the s^-1 x s^-1 block of large pixels.
#[test]
fn resized_camera_projects_points_to_scaled_coordinates() {
    let cam = Camera::from_rotation_center(
        intr(),
        DMat3::from_axis_angle(DVec3::new(1.0, 2.0, 0.5).normalize(), 0.4),
        DVec3::new(0.3, -0.2, -5.0),
    );
    let small = cam.resized(90, 160);
    for p in [DVec3::new(0.1, 0.2, 0.3), DVec3::new(-1.0, 0.5, 2.0)] {
        let (u, v, z) = cam.project_point(p);
        let (us, vs, zs) = small.project_point(p);
        assert!((us - u / 8.0).abs() < 1e-9 && (vs - v / 8.0).abs() < 1e-9);
        assert_eq!(z, zs);
    }
    assert_eq!(small.camera_from_world, cam.camera_from_world);
}

#[test]
fn rotation_centre_constructor_round_trips() {
    let rot = DMat3::from_axis_angle(DVec3::new(-0.3, 0.2, 1.0).normalize(), 2.0);
    let c = DVec3::new(1.0, -2.0, 3.0);
    let cam = Camera::from_rotation_center(intr(), rot, c);
    assert!((cam.center() - c).length() < 1e-12);
    assert!((cam.rotation() - rot).abs_diff_eq(DMat3::ZERO, 1e-15));
    // The camera looks along its +z axis.
    assert!((cam.view_direction() - rot.transpose() * DVec3::Z).length() < 1e-15);
}
