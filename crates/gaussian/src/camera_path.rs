//! Camera paths for rendering videos: interpolation through keyframe cameras and orbits.
//!
//! Interpolation is piecewise between consecutive keyframes: rotations (world-from-camera, as
//! unit quaternions) are slerped along the shorter arc, camera centres and intrinsics are lerped.
//! Orbits circle a centre at a fixed radius and elevation above the plane orthogonal to `up`,
//! every camera looking at the centre with its image "up" (OpenCV -y) along the world `up`.
//!
//! A [`tour`] is the smooth video path through a capture: the cameras' azimuths about `up`
//! around the centre they look at fix the arc it sweeps (the whole circle when they surround
//! the centre, else the range they cover), and the radius and elevation along it are the
//! cameras' own, smoothed by a kernel in azimuth, so that it never jumps between cameras that
//! are far apart in the capture's order, never comes nearer the centre than the nearest camera,
//! and keeps the centre in the middle of every frame.

use glam::{DMat3, DQuat, DVec3};

use crate::camera::{plain_numbers, Camera, Intrinsics};

/// An impossible camera path request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraPathError {
    /// [`interpolate`] was given an empty keyframe list.
    #[error("a camera path needs at least one keyframe")]
    NoKeyframes,
    /// The orbit radius (world units) is not finite and positive.
    #[error("orbit radius must be positive and finite, got {0}")]
    Radius(f64),
    /// The orbit elevation (radians) is NaN or not strictly inside `(-pi/2, pi/2)`.
    #[error("orbit elevation must lie strictly between -90 and 90 degrees, got {0} rad")]
    Elevation(f64),
    /// The orbit `up` axis cannot be normalised (zero, or not finite).
    #[error("orbit up axis must be a finite non-zero vector, got {}", plain_numbers(&.0.to_array()))]
    Up(DVec3),
    /// [`orbit_from`]'s start camera lies on the line through `center` along `up`, so it has no
    /// horizontal direction to start from (for [`tour`]: every camera does).
    #[error("orbit start camera sits on the orbit axis through the centre")]
    OnAxis,
}

fn lerp(a: f64, b: f64, s: f64) -> f64 {
    a + (b - a) * s
}

fn lerp_intrinsics(a: &Intrinsics, b: &Intrinsics, s: f64) -> Intrinsics {
    Intrinsics {
        fx: lerp(a.fx, b.fx, s),
        fy: lerp(a.fy, b.fy, s),
        cx: lerp(a.cx, b.cx, s),
        cy: lerp(a.cy, b.cy, s),
        width: lerp(a.width as f64, b.width as f64, s).round() as u32,
        height: lerp(a.height as f64, b.height as f64, s).round() as u32,
    }
}

/// The camera a fraction `s` in `[0, 1]` of the way from `a` to `b`.
pub fn interpolate_pair(a: &Camera, b: &Camera, s: f64) -> Camera {
    let qa = DQuat::from_mat3(&a.rotation().transpose()).normalize();
    let qb = DQuat::from_mat3(&b.rotation().transpose()).normalize();
    let world_from_camera_rot = DMat3::from_quat(qa.slerp(qb, s).normalize());
    let center = a.center().lerp(b.center(), s);
    Camera::from_rotation_center(
        lerp_intrinsics(&a.intrinsics, &b.intrinsics, s),
        world_from_camera_rot.transpose(),
        center,
    )
}

/// `n_frames` cameras evenly spaced in the keyframe parameter: frame `f` sits at
/// `t = f (K - 1) / (n_frames - 1)` (keyframe `floor(t)`, fraction `t - floor(t)`), so the first
/// and last frames are the first and last keyframes, and a frame that lands on a keyframe
/// reproduces it exactly. Image sizes are lerped and rounded (they stay fixed when all
/// keyframes share one size).
pub fn interpolate(keyframes: &[Camera], n_frames: usize) -> Result<Vec<Camera>, CameraPathError> {
    let k = keyframes.len();
    if k == 0 {
        return Err(CameraPathError::NoKeyframes);
    }
    if k == 1 || n_frames <= 1 {
        return Ok(vec![keyframes[0]; n_frames]);
    }
    Ok((0..n_frames)
        .map(|f| {
            let t = f as f64 * (k - 1) as f64 / (n_frames - 1) as f64;
            let seg = (t.floor() as usize).min(k - 2);
            let s = t - seg as f64;
            if s == 0.0 {
                keyframes[seg]
            } else if s == 1.0 {
                keyframes[seg + 1]
            } else {
                interpolate_pair(&keyframes[seg], &keyframes[seg + 1], s)
            }
        })
        .collect())
}

/// A camera at `eye` looking at `target`, image up along `up` (OpenCV axes: z towards the
/// target, y = image down, x = image right). `None` when `up` is parallel to the view axis.
pub fn look_at(intrinsics: Intrinsics, eye: DVec3, target: DVec3, up: DVec3) -> Option<Camera> {
    let z = (target - eye).try_normalize()?;
    let x = (-up).cross(z).try_normalize()?;
    let y = z.cross(x);
    let world_from_camera_rot = DMat3::from_cols(x, y, z);
    Some(Camera::from_rotation_center(
        intrinsics,
        world_from_camera_rot.transpose(),
        eye,
    ))
}

/// The point nearest, in the least-squares sense, to the optical axes of `cameras`: what a
/// capture looks at. `None` for fewer than two cameras or (nearly) parallel axes.
///
/// Each axis contributes its orthogonal projector `P = I - d d^T`; the point solves
/// `(sum P) x = sum P c`. For parallel axes the matrix is singular: its determinant is compared
/// with the cube of its trace (scale-free; about `1e-9` means axes within about `1e-4` rad of
/// each other).
pub fn look_at_point(cameras: &[Camera]) -> Option<DVec3> {
    if cameras.len() < 2 {
        return None;
    }
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for c in cameras {
        let d = c.view_direction().normalize();
        let p = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * c.center();
    }
    let tr = a.x_axis.x + a.y_axis.y + a.z_axis.z;
    // A NaN determinant (non-finite poses) fails the comparison too.
    let conditioned = a.determinant().abs() > 1e-9 * tr * tr * tr;
    if !conditioned {
        return None;
    }
    let x = a.inverse() * b;
    x.is_finite().then_some(x)
}

/// The mean image-up direction (camera `-y`) of `cameras` in world coordinates, normalised;
/// `None` when there are none or their directions cancel out.
pub fn mean_up(cameras: &[Camera]) -> Option<DVec3> {
    let sum: DVec3 = cameras
        .iter()
        .map(|c| c.rotation().transpose() * DVec3::NEG_Y)
        .sum();
    sum.try_normalize()
}

/// `n_frames` cameras on a circle around `center` (angles `2 pi f / n_frames`, so the path
/// loops without repeating a frame) at distance `radius` and elevation `elevation` (radians)
/// above the plane orthogonal to `up`, each looking at `center`. The first camera lies in the
/// direction `up.any_orthonormal_vector()` from the axis; use [`orbit_from`] to start at a
/// given camera instead.
pub fn orbit(
    intrinsics: Intrinsics,
    center: DVec3,
    radius: f64,
    elevation: f64,
    n_frames: usize,
    up: DVec3,
) -> Result<Vec<Camera>, CameraPathError> {
    let up_n = check_up(up)?;
    orbit_with_start(
        intrinsics,
        center,
        radius,
        elevation,
        (n_frames, &|f| {
            std::f64::consts::TAU * f as f64 / n_frames as f64
        }),
        up_n,
        up_n.any_orthonormal_vector(),
    )
}

/// An orbit around `center` that starts at `start`'s position (its radius and elevation come
/// from that position) and uses `start`'s intrinsics.
pub fn orbit_from(
    start: &Camera,
    center: DVec3,
    n_frames: usize,
    up: DVec3,
) -> Result<Vec<Camera>, CameraPathError> {
    start_on_orbit(
        start,
        center,
        n_frames,
        &|f| std::f64::consts::TAU * f as f64 / n_frames as f64,
        up,
    )
}

/// `n_frames` cameras on the orbit of [`orbit_from`], `step` radians apart around `up`
/// (an arc of `step (n_frames - 1)`): a path whose consecutive frames are a fixed, small
/// rotation and translation apart.
pub fn arc_from(
    start: &Camera,
    center: DVec3,
    step: f64,
    n_frames: usize,
    up: DVec3,
) -> Result<Vec<Camera>, CameraPathError> {
    start_on_orbit(start, center, n_frames, &|f| step * f as f64, up)
}

/// `n_frames` cameras on the orbit through `start` around `center`, frame `f` at angle
/// `theta(f)` from `start`.
fn start_on_orbit(
    start: &Camera,
    center: DVec3,
    n_frames: usize,
    theta: &dyn Fn(usize) -> f64,
    up: DVec3,
) -> Result<Vec<Camera>, CameraPathError> {
    let up_n = check_up(up)?;
    let offset = start.center() - center;
    let height = offset.dot(up_n);
    let horizontal = offset - height * up_n;
    let e1 = horizontal.try_normalize().ok_or(CameraPathError::OnAxis)?;
    let radius = offset.length();
    let elevation = height.atan2(horizontal.length());
    orbit_with_start(
        start.intrinsics,
        center,
        radius,
        elevation,
        (n_frames, theta),
        up_n,
        e1,
    )
}

/// The widest gap (radians) between neighbouring camera azimuths for which a [`tour`] circles
/// the whole way round: with no gap wider than a quarter turn the cameras surround the centre.
pub const TOUR_CLOSED_GAP: f64 = std::f64::consts::FRAC_PI_2;

/// The kernel width (radians) of the smoothing of radius and elevation along a [`tour`]: the
/// standard deviation of a Gaussian in azimuth, wide enough that neighbouring cameras at
/// different heights or distances give a gentle slope, not a corner.
pub const TOUR_SMOOTHING: f64 = 0.5;

/// `n_frames` cameras on a smooth path around `center` through the region the `cameras` see it
/// from, each looking at `center` with its image up along `up`, with the first camera's
/// intrinsics.
///
/// Each camera's position is taken in cylindrical terms about the axis through `center` along
/// `up`: azimuth, elevation and distance. When no two neighbouring azimuths are more than
/// [`TOUR_CLOSED_GAP`] apart the path is a loop starting at the first camera's azimuth
/// (`2 pi f / n_frames`, no frame repeated); otherwise it sweeps, at a constant angular step,
/// the arc the cameras cover (the circle without its widest gap), from one end to the other.
/// At each azimuth the elevation and the distance are averages over all cameras weighted by a
/// Gaussian of their azimuth difference ([`TOUR_SMOOTHING`], wrapped around the circle), so
/// they vary smoothly and the distance stays within the cameras' range. Cameras on the axis
/// have no azimuth and are left out; [`CameraPathError::OnAxis`] when all are.
pub fn tour(
    cameras: &[Camera],
    center: DVec3,
    up: DVec3,
    n_frames: usize,
) -> Result<Vec<Camera>, CameraPathError> {
    use std::f64::consts::{PI, TAU};
    let up_n = check_up(up)?;
    let first = cameras.first().ok_or(CameraPathError::NoKeyframes)?;
    let e1 = up_n.any_orthonormal_vector();
    let e2 = up_n.cross(e1);
    // (azimuth, elevation, distance) of every camera off the axis.
    let mut polar = Vec::with_capacity(cameras.len());
    for c in cameras {
        let offset = c.center() - center;
        let height = offset.dot(up_n);
        let horizontal = offset - height * up_n;
        // A camera on the axis has no azimuth: it does not shape the path.
        if horizontal.length() <= 1e-9 * offset.length() || !horizontal.is_finite() {
            continue;
        }
        let azimuth = horizontal.dot(e2).atan2(horizontal.dot(e1)).rem_euclid(TAU);
        polar.push((azimuth, height.atan2(horizontal.length()), offset.length()));
    }
    if polar.is_empty() {
        return Err(CameraPathError::OnAxis);
    }
    let mut sorted: Vec<f64> = polar.iter().map(|p| p.0).collect();
    sorted.sort_by(f64::total_cmp);
    // The widest gap between neighbouring azimuths, the wrap-around one included.
    let (mut gap, mut gap_end) = (sorted[0] + TAU - sorted[sorted.len() - 1], sorted[0]);
    for w in sorted.windows(2) {
        if w[1] - w[0] > gap {
            (gap, gap_end) = (w[1] - w[0], w[1]);
        }
    }
    let closed = gap <= TOUR_CLOSED_GAP;
    let azimuth = |f: usize| -> f64 {
        if closed {
            polar[0].0 + TAU * f as f64 / n_frames as f64
        } else {
            let span = TAU - gap;
            let t = if n_frames > 1 {
                f as f64 / (n_frames - 1) as f64
            } else {
                0.5
            };
            gap_end + span * t
        }
    };
    (0..n_frames)
        .map(|f| {
            let phi = azimuth(f);
            let (mut weight, mut elevation, mut distance) = (0.0, 0.0, 0.0);
            for &(a, e, r) in &polar {
                let d = (phi - a + PI).rem_euclid(TAU) - PI;
                let w = (-0.5 * (d / TOUR_SMOOTHING).powi(2)).exp();
                weight += w;
                elevation += w * e;
                distance += w * r;
            }
            // Every weight is at least exp(-0.5 (pi / TOUR_SMOOTHING)^2), about 3e-9: no
            // division by zero.
            let (elevation, distance) = (elevation / weight, distance / weight);
            let (s, c) = phi.sin_cos();
            let (se, ce) = elevation.sin_cos();
            let eye = center + distance * (ce * (c * e1 + s * e2) + se * up_n);
            look_at(first.intrinsics, eye, center, up_n)
                .ok_or(CameraPathError::Elevation(elevation))
        })
        .collect()
}

fn check_up(up: DVec3) -> Result<DVec3, CameraPathError> {
    up.try_normalize().ok_or(CameraPathError::Up(up))
}

fn orbit_with_start(
    intrinsics: Intrinsics,
    center: DVec3,
    radius: f64,
    elevation: f64,
    (n_frames, theta): (usize, &dyn Fn(usize) -> f64),
    up: DVec3,
    e1: DVec3,
) -> Result<Vec<Camera>, CameraPathError> {
    if !(radius.is_finite() && radius > 0.0) {
        return Err(CameraPathError::Radius(radius));
    }
    if elevation.is_nan() || elevation.abs() >= std::f64::consts::FRAC_PI_2 {
        return Err(CameraPathError::Elevation(elevation));
    }
    let e2 = up.cross(e1);
    let (sin_e, cos_e) = elevation.sin_cos();
    (0..n_frames)
        .map(|f| {
            let (s, c) = theta(f).sin_cos();
            let eye = center + radius * (cos_e * (c * e1 + s * e2) + sin_e * up);
            // |elevation| < 90 degrees keeps the view axis off `up`, so look_at succeeds.
            look_at(intrinsics, eye, center, up).ok_or(CameraPathError::Elevation(elevation))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat4;

    /// Cameras on a tilted ring around `target`, looking at it with image up along +y.
    fn ring(n: usize, target: DVec3) -> Vec<Camera> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.4;
                let eye = DVec3::new(3.0 * a.cos(), 1.0, 3.0 * a.sin()) + target;
                look_at(intr(), eye, target, DVec3::NEG_Y).unwrap()
            })
            .collect()
    }

    #[test]
    fn look_at_point_finds_the_common_target_and_mean_up_the_image_up() {
        let target = DVec3::new(1.0, 2.0, 3.0);
        let p = look_at_point(&ring(5, target)).unwrap();
        assert!((p - target).length() < 1e-9, "{p}");
        let up = mean_up(&ring(5, target)).unwrap();
        assert!(up.dot(DVec3::NEG_Y) > 0.9, "{up}");
    }

    #[test]
    fn look_at_point_is_none_for_parallel_axes_or_a_single_camera() {
        let target = DVec3::new(1.0, 2.0, 3.0);
        assert!(look_at_point(&ring(1, target)).is_none());
        assert!(look_at_point(&[]).is_none());
        // Cameras side by side, all looking along +z.
        let parallel: Vec<Camera> = (0..4)
            .map(|i| {
                let eye = DVec3::new(i as f64, 0.0, 0.0);
                look_at(intr(), eye, eye + DVec3::Z, DVec3::NEG_Y).unwrap()
            })
            .collect();
        assert!(look_at_point(&parallel).is_none());
        assert!(mean_up(&[]).is_none());
    }

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: 50.0,
            fy: 55.0,
            cx: 31.5,
            cy: 24.0,
            width: 64,
            height: 48,
        }
    }

    fn cam(axis: DVec3, angle: f64, center: DVec3, fx: f64) -> Camera {
        let rot = DMat3::from_axis_angle(axis.normalize(), angle);
        let mut k = intr();
        k.fx = fx;
        Camera::from_rotation_center(k, rot, center)
    }

    fn mat_close(a: DMat4, b: DMat4, tol: f64) -> bool {
        a.to_cols_array()
            .iter()
            .zip(b.to_cols_array())
            .all(|(x, y)| (x - y).abs() <= tol)
    }

    #[test]
    fn interpolation_reproduces_keyframes() {
        let keys = [
            cam(
                DVec3::new(0.2, 1.0, 0.1),
                0.3,
                DVec3::new(1.0, 2.0, 3.0),
                50.0,
            ),
            cam(
                DVec3::new(-0.4, 0.3, 1.0),
                1.7,
                DVec3::new(-1.0, 0.5, 2.0),
                60.0,
            ),
            cam(
                DVec3::new(1.0, 0.0, 0.0),
                -2.5,
                DVec3::new(0.0, 0.0, -4.0),
                40.0,
            ),
        ];
        // 9 frames over 2 segments: frames 0, 4, 8 land on keyframes.
        let path = interpolate(&keys, 9).unwrap();
        assert_eq!(path.len(), 9);
        assert_eq!(path[0], keys[0]);
        assert_eq!(path[4], keys[1]);
        assert_eq!(path[8], keys[2]);
        // Interpolating a pair at its ends reproduces the ends (up to rounding).
        for (a, b) in [(keys[0], keys[1]), (keys[1], keys[2])] {
            let p0 = interpolate_pair(&a, &b, 0.0);
            let p1 = interpolate_pair(&a, &b, 1.0);
            assert!(mat_close(p0.camera_from_world, a.camera_from_world, 1e-12));
            assert!(mat_close(p1.camera_from_world, b.camera_from_world, 1e-12));
            assert!((p1.intrinsics.fx - b.intrinsics.fx).abs() < 1e-12);
        }
    }

    #[test]
    fn interpolation_midpoint_is_halfway() {
        let a = cam(DVec3::Y, 0.2, DVec3::new(0.0, 0.0, 0.0), 50.0);
        let b = cam(DVec3::Y, 1.0, DVec3::new(2.0, 0.0, 4.0), 70.0);
        let m = interpolate_pair(&a, &b, 0.5);
        // Rotation about a common axis: the midpoint is the mean angle.
        let expect = DMat3::from_axis_angle(DVec3::Y, 0.6);
        let r = m.rotation();
        for (x, y) in r.to_cols_array().iter().zip(expect.to_cols_array()) {
            assert!((x - y).abs() < 1e-12);
        }
        assert!((m.center() - DVec3::new(1.0, 0.0, 2.0)).length() < 1e-12);
        assert!((m.intrinsics.fx - 60.0).abs() < 1e-12);
        // Every interpolated pose stays a rigid transform.
        let rtr = r.transpose() * r;
        assert!((rtr - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-12));
    }

    #[test]
    fn interpolation_edge_cases() {
        assert_eq!(interpolate(&[], 5), Err(CameraPathError::NoKeyframes));
        let a = cam(DVec3::Z, 0.1, DVec3::ONE, 50.0);
        assert_eq!(interpolate(&[a], 3).unwrap(), vec![a; 3]);
        assert!(interpolate(&[a, a], 0).unwrap().is_empty());
    }

    #[test]
    fn orbit_cameras_look_at_the_centre() {
        let center = DVec3::new(0.5, -1.0, 2.0);
        let up = DVec3::new(0.0, -1.0, 0.2);
        let path = orbit(intr(), center, 3.0, 0.4, 12, up).unwrap();
        assert_eq!(path.len(), 12);
        let up_n = up.normalize();
        for c in &path {
            let (u, v, z) = c.project_point(center);
            assert!((u - intr().cx).abs() < 1e-9, "u = {u}");
            assert!((v - intr().cy).abs() < 1e-9, "v = {v}");
            assert!((z - 3.0).abs() < 1e-12);
            let off = c.center() - center;
            assert!((off.length() - 3.0).abs() < 1e-12);
            assert!((off.normalize().dot(up_n) - 0.4f64.sin()).abs() < 1e-12);
            // A point above the centre (along up) appears above it in the image (smaller v).
            let (_, v_up, _) = c.project_point(center + 0.1 * up_n);
            assert!(v_up < v);
        }
        // Consecutive cameras are 30 degrees apart around the axis.
        let a = path[0].center() - center;
        let b = path[1].center() - center;
        let ha = a - a.dot(up_n) * up_n;
        let hb = b - b.dot(up_n) * up_n;
        assert!((ha.angle_between(hb) - std::f64::consts::TAU / 12.0).abs() < 1e-12);
    }

    #[test]
    fn orbit_from_starts_at_the_camera() {
        let center = DVec3::new(0.0, 0.0, 0.0);
        let start = look_at(intr(), DVec3::new(3.0, 1.0, 0.5), center, DVec3::Z).unwrap();
        let path = orbit_from(&start, center, 8, DVec3::Z).unwrap();
        assert!(mat_close(
            path[0].camera_from_world,
            start.camera_from_world,
            1e-12
        ));
    }

    /// The angle of the rotation taking one camera's axes to the other's, in radians.
    fn rotation_angle(a: &Camera, b: &Camera) -> f64 {
        let r = a.rotation().transpose() * b.rotation();
        let cos = ((r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0) / 2.0).clamp(-1.0, 1.0);
        cos.acos()
    }

    #[test]
    fn arc_frames_are_a_fixed_step_apart() {
        let center = DVec3::new(0.5, -0.2, 0.1);
        let start = look_at(intr(), DVec3::new(3.0, 1.0, 1.5), center, DVec3::Z).unwrap();
        let step = 1.5f64.to_radians();
        let path = arc_from(&start, center, step, 12, DVec3::Z).unwrap();
        assert_eq!(path.len(), 12);
        assert!(mat_close(
            path[0].camera_from_world,
            start.camera_from_world,
            1e-12
        ));
        let radius = (start.center() - center).length();
        let height = (start.center() - center).dot(DVec3::Z);
        // Centres on the circle of the start's height: chord 2 r' sin(step / 2).
        let r_h = (radius * radius - height * height).sqrt();
        for w in path.windows(2) {
            let chord = (w[1].center() - w[0].center()).length();
            assert!(
                (chord - 2.0 * r_h * (step / 2.0).sin()).abs() < 1e-12,
                "{chord}"
            );
            // Each frame is the last turned by `step` about the up axis.
            assert!((rotation_angle(&w[0], &w[1]) - step).abs() < 1e-9);
        }
    }

    #[test]
    fn orbit_rejects_bad_input() {
        let c = DVec3::ZERO;
        assert!(matches!(
            orbit(intr(), c, -1.0, 0.0, 4, DVec3::Y),
            Err(CameraPathError::Radius(_))
        ));
        assert!(matches!(
            orbit(intr(), c, 1.0, 1.6, 4, DVec3::Y),
            Err(CameraPathError::Elevation(_))
        ));
        assert!(matches!(
            orbit(intr(), c, 1.0, 0.0, 4, DVec3::ZERO),
            Err(CameraPathError::Up(_))
        ));
        assert!(matches!(
            orbit(intr(), c, 1.0, f64::NAN, 4, DVec3::Y),
            Err(CameraPathError::Elevation(_))
        ));
    }

    /// Cameras looking at `target` from the given (azimuth, elevation, distance) about +z, in
    /// the given order.
    fn scattered(target: DVec3, polar: &[(f64, f64, f64)]) -> Vec<Camera> {
        polar
            .iter()
            .map(|&(a, e, r)| {
                let eye = target + r * DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
                look_at(intr(), eye, target, DVec3::Z).unwrap()
            })
            .collect()
    }

    /// Pseudo-random numbers in [0, 1), reproducible.
    fn uniform(n: usize, seed: u64) -> Vec<f64> {
        let mut x = seed;
        (0..n)
            .map(|_| {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (x >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    /// A camera's azimuth about +z around `target`.
    fn azimuth(c: &Camera, target: DVec3) -> f64 {
        let d = c.center() - target;
        d.y.atan2(d.x)
    }

    #[test]
    fn a_tour_round_cameras_in_random_order_steps_evenly_and_keeps_its_distance() {
        // 40 cameras all round a target, in random order, at random heights and distances: the
        // order a NeRF-synthetic capture lists its cameras in.
        let target = DVec3::new(0.5, -1.0, 2.0);
        let u = uniform(120, 7);
        let polar: Vec<_> = (0..40)
            .map(|i| {
                let a = std::f64::consts::TAU * u[3 * i];
                (a, 0.1 + 1.0 * u[3 * i + 1], 3.0 + 2.0 * u[3 * i + 2])
            })
            .collect();
        let cams = scattered(target, &polar);
        let n = 48;
        let path = tour(&cams, target, DVec3::Z, n).unwrap();
        assert_eq!(path.len(), n);
        // A loop from the first camera's azimuth, a constant step round the axis.
        let step = std::f64::consts::TAU / n as f64;
        assert!((azimuth(&path[0], target) - azimuth(&cams[0], target)).abs() < 1e-9);
        for (i, w) in path.windows(2).enumerate() {
            let turn =
                (azimuth(&w[1], target) - azimuth(&w[0], target)).rem_euclid(std::f64::consts::TAU);
            assert!((turn - step).abs() < 1e-9, "frame {i}: {turn}");
            // No jumps: consecutive frames are little more than the turn's arc apart (a
            // frame-to-frame path through the cameras in their order moves up to 10 units).
            let moved = (w[1].center() - w[0].center()).length();
            let r = (w[0].center() - target).length();
            assert!(moved < 1.25 * step * r, "frame {i}: {moved}");
        }
        for c in &path {
            // Never nearer than the nearest camera, never farther than the farthest.
            let r = (c.center() - target).length();
            assert!((3.0..=5.0).contains(&r), "{r}");
            // The target at the principal point of every frame.
            let p = c.camera_from_world.transform_point3(target);
            let (x, y) = (
                c.intrinsics.fx * p.x / p.z + c.intrinsics.cx,
                c.intrinsics.fy * p.y / p.z + c.intrinsics.cy,
            );
            assert!(
                p.z > 0.0
                    && (x - c.intrinsics.cx).abs() < 1e-6
                    && (y - c.intrinsics.cy).abs() < 1e-6
            );
        }
    }

    #[test]
    fn a_tour_of_cameras_on_one_side_sweeps_their_arc() {
        // Cameras between azimuths 1.0 and 2.0 only (a forward-facing capture), shuffled.
        let target = DVec3::ZERO;
        let order = [3, 0, 5, 1, 4, 2];
        let polar: Vec<_> = order
            .iter()
            .map(|&k| (1.0 + 0.2 * k as f64, 0.3, 4.0))
            .collect();
        let cams = scattered(target, &polar);
        let path = tour(&cams, target, DVec3::Z, 11).unwrap();
        assert!((azimuth(&path[0], target) - 1.0).abs() < 1e-9);
        assert!((azimuth(&path[10], target) - 2.0).abs() < 1e-9);
        for w in path.windows(2) {
            let turn = azimuth(&w[1], target) - azimuth(&w[0], target);
            assert!((turn - 0.1).abs() < 1e-9, "{turn}");
        }
        // All cameras at one height and distance: so is the path.
        for c in &path {
            assert!(((c.center() - target).length() - 4.0).abs() < 1e-9);
            assert!(((c.center() - target).z - 4.0 * 0.3f64.sin()).abs() < 1e-9);
        }
        // Cameras on the axis only: no path.
        let above = scattered(target, &[(0.0, std::f64::consts::FRAC_PI_2, 2.0)]);
        assert!(tour(&above, target, DVec3::Z, 4).is_err());
        assert!(tour(&[], target, DVec3::Z, 4).is_err());
    }
}
