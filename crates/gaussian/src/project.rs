//! EWA projection of 3D Gaussians to screen-space 2D Gaussians, forward and exact backward.
//!
//! Convention: gsplat 1.5.3's pure-PyTorch reference (`_quat_scale_to_covar_preci`,
//! `_world_to_cam`, `_persp_proj`, `_fully_fused_projection`), as pinned by the oracle:
//!
//! * `q` is normalised as `q / max(|q|, 1e-12)`; `R = R(q)`, `S = diag(exp(log_scales))`,
//!   `Sigma = R S S^T R^T`; `exp` is [`Real::exp_fixed`] (in `f32` the project's exponential,
//!   within 2 ulp of the correctly rounded one, which vector code reproduces bit for bit).
//! * `p = W m + t` and `Sigma_c = W Sigma W^T` with `(W, t)` the camera's `camera_from_world`.
//! * The EWA Jacobian uses a clamped position: `x' = z clamp(x / z, -lim_x_neg, lim_x_pos)` with
//!   `lim_x_pos = (width - cx) / fx + 0.3 tan_fovx`, `lim_x_neg = cx / fx + 0.3 tan_fovx`,
//!   `tan_fovx = 0.5 width / fx` (likewise in y);
//!   `J = [[fx/z, 0, -fx x'/z^2], [0, fy/z, -fy y'/z^2]]`, `cov2d = J Sigma_c J^T + eps2d I`.
//! * `means2d = (fx x / z + cx, fy y / z + cy)` uses the unclamped position; `depth = z`.
//! * `det = max(a c - b^2, 1e-10)` of the dilated `cov2d = [[a, b], [b, c]]`;
//!   `conic = (c / det, -b / det, a / det)`.
//! * `radii = (ceil(3.33 sqrt(a)), ceil(3.33 sqrt(c)))`, set to `(0, 0)` (culled) unless
//!   `det > 0` (after the clamp, so only a NaN fails it), `near < z < far`, and the radius box
//!   overlaps the image: `mx + rx > 0`, `mx - rx < width`, `my + ry > 0`, `my - ry < height`.
//!
//! Outputs are computed for every Gaussian, culled or not (as the reference does); only `radii`
//! tells which are visible. The backward gives culled Gaussians zero gradient, passes the clamp
//! gradient where `-lim_neg <= x / z <= lim_pos` (PyTorch's `clamp` backward) and the
//! determinant gradient where `det >= 1e-10`.
//!
//! Matrices here are row-major `[[T; 3]; 3]` (`m[row][col]`).
//!
//! Both passes run in parallel work items of 1,024 Gaussians, each a plain loop over
//! its Gaussians. In `f32` the loop is compiled for the best instruction set `pulp` finds at
//! run time (no `-C target-cpu` needed), where the compiler vectorises the forward pass across
//! Gaussians; only IEEE operations without fused multiply-adds are involved, so every
//! instruction set gives the bits of the generic code (a unit test compares them).

use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::scene::quat_to_rotmat;
use crate::Real;

/// Settings of the projection; the defaults are gsplat's.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectSettings {
    /// Added to the diagonal of every 2D covariance (pixels squared): a low-pass filter.
    pub eps2d: f64,
    /// Gaussians with view depth `<= near` are culled.
    pub near: f64,
    /// Gaussians with view depth `>= far` are culled.
    pub far: f64,
    /// Screen-space radius in standard deviations, per axis.
    pub radius_sigma: f64,
}

impl Default for ProjectSettings {
    fn default() -> Self {
        ProjectSettings {
            eps2d: 0.3,
            near: 0.01,
            far: 1e10,
            radius_sigma: 3.33,
        }
    }
}

/// Projected 2D Gaussians, one entry per input Gaussian.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Projected<T> {
    /// Pixel coordinates of the projected means (pixel centres at `i + 0.5`).
    pub means2d: Vec<[T; 2]>,
    /// Inverse 2D covariances `(a, b, c)`: `sigma(d) = 0.5 (a dx^2 + c dy^2) + b dx dy`.
    pub conics: Vec<[T; 3]>,
    /// View depth (camera z).
    pub depths: Vec<T>,
    /// Screen-space radii in pixels per axis; `[0, 0]` marks a culled Gaussian.
    pub radii: Vec<[u32; 2]>,
}

impl<T> Projected<T> {
    /// Whether Gaussian `i` survived culling.
    pub fn is_visible(&self, i: usize) -> bool {
        self.radii[i][0] > 0 && self.radii[i][1] > 0
    }
}

/// Gradients of a scalar loss with respect to the projection inputs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ProjectionGrads<T> {
    /// With respect to the world-space means, one `[x, y, z]` per Gaussian.
    pub means: Vec<[T; 3]>,
    /// With respect to the unnormalised quaternions.
    pub quats: Vec<[T; 4]>,
    /// With respect to the per-axis log-scales, one `[x, y, z]` per Gaussian.
    pub log_scales: Vec<[T; 3]>,
}

type M3<T> = [[T; 3]; 3];

/// The camera and settings converted to `T` once.
#[derive(Clone, Copy, Debug)]
struct CamT<T> {
    rot: M3<T>,
    trans: [T; 3],
    fx: T,
    fy: T,
    cx: T,
    cy: T,
    width: T,
    height: T,
    lim_x_pos: T,
    lim_x_neg: T,
    lim_y_pos: T,
    lim_y_neg: T,
    eps2d: T,
    near: T,
    far: T,
    radius_sigma: T,
}

impl<T: Real> CamT<T> {
    fn new(camera: &Camera, s: &ProjectSettings) -> Self {
        let k = &camera.intrinsics;
        let m = camera.camera_from_world;
        let (w, h) = (k.width as f64, k.height as f64);
        let tan_fovx = 0.5 * w / k.fx;
        let tan_fovy = 0.5 * h / k.fy;
        let l = T::lit;
        CamT {
            // glam is column-major: row r, column c is col(c)[r].
            rot: [0, 1, 2].map(|r| [0, 1, 2].map(|c| l(m.col(c)[r]))),
            trans: [0, 1, 2].map(|r| l(m.col(3)[r])),
            fx: l(k.fx),
            fy: l(k.fy),
            cx: l(k.cx),
            cy: l(k.cy),
            width: l(w),
            height: l(h),
            lim_x_pos: l((w - k.cx) / k.fx + 0.3 * tan_fovx),
            lim_x_neg: l(k.cx / k.fx + 0.3 * tan_fovx),
            lim_y_pos: l((h - k.cy) / k.fy + 0.3 * tan_fovy),
            lim_y_neg: l(k.cy / k.fy + 0.3 * tan_fovy),
            eps2d: l(s.eps2d),
            near: l(s.near),
            far: l(s.far),
            radius_sigma: l(s.radius_sigma),
        }
    }
}

/// `[f(0), f(1), f(2)]`, spelled out so that it always inlines (`array::map` may not).
#[inline(always)]
fn v3<T>(f: impl Fn(usize) -> T) -> [T; 3] {
    [f(0), f(1), f(2)]
}

/// The 3x3 matrix with entries `f(row, col)`.
#[inline(always)]
fn m3<T>(f: impl Fn(usize, usize) -> T) -> [[T; 3]; 3] {
    [v3(|j| f(0, j)), v3(|j| f(1, j)), v3(|j| f(2, j))]
}

#[inline(always)]
fn matmul<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    m3(|i, j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j])
}

#[inline(always)]
fn transpose<T: Real>(a: &M3<T>) -> M3<T> {
    m3(|i, j| a[j][i])
}

#[inline(always)]
fn matvec<T: Real>(a: &M3<T>, v: &[T; 3]) -> [T; 3] {
    v3(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// `a^T v`.
#[inline(always)]
fn matvec_t<T: Real>(a: &M3<T>, v: &[T; 3]) -> [T; 3] {
    v3(|i| a[0][i] * v[0] + a[1][i] * v[1] + a[2][i] * v[2])
}

/// F.normalize semantics: `q / max(|q|, 1e-12)`. Returns the unit quaternion, the divisor and
/// whether the norm was clamped (then the divisor does not depend on `q`).
#[inline(always)]
fn normalize_quat_ref<T: Real>(q: &[T; 4]) -> ([T; 4], T, bool) {
    let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let eps = T::lit(1e-12);
    let clamped = norm < eps;
    let denom = if clamped { eps } else { norm };
    (
        [q[0] / denom, q[1] / denom, q[2] / denom, q[3] / denom],
        denom,
        clamped,
    )
}

/// The world-space covariance and the intermediates its backward needs.
struct Covariance<T> {
    qn: [T; 4],
    denom: T,
    norm_clamped: bool,
    rot: M3<T>,
    scale: [T; 3],
    /// `M = R S`.
    m: M3<T>,
    sigma: M3<T>,
}

#[inline(always)]
fn covariance<T: Real>(quat: &[T; 4], log_scale: &[T; 3]) -> Covariance<T> {
    let (qn, denom, norm_clamped) = normalize_quat_ref(quat);
    let rot = quat_to_rotmat(qn);
    // The exponential the vector code reproduces bit for bit (`exp_f32` in `f32`).
    let scale = v3(|j| log_scale[j].exp_fixed());
    let m = m3(|i, j| rot[i][j] * scale[j]);
    let sigma = matmul(&m, &transpose(&m));
    Covariance {
        qn,
        denom,
        norm_clamped,
        rot,
        scale,
        m,
        sigma,
    }
}

/// The screen-space Gaussian of one 3D Gaussian and the intermediates its backward needs.
struct Screen<T> {
    /// Camera-space mean.
    p: [T; 3],
    sigma_c: M3<T>,
    /// `x / z` and `y / z` before the clamp.
    u: [T; 2],
    /// After the clamp.
    u_clamped: [T; 2],
    /// The Jacobian's non-zero entries `(J00, J02, J11, J12)`.
    j: [T; 4],
    /// The dilated 2D covariance `(a, b, c)`.
    cov: [T; 3],
    det_raw: T,
    det: T,
    mean2d: [T; 2],
    conic: [T; 3],
}

#[inline(always)]
fn screen<T: Real>(cam: &CamT<T>, mean: &[T; 3], sigma: &M3<T>) -> Screen<T> {
    let pw = matvec(&cam.rot, mean);
    let p = v3(|i| pw[i] + cam.trans[i]);
    let sigma_c = matmul(&matmul(&cam.rot, sigma), &transpose(&cam.rot));
    let [tx, ty, tz] = p;
    let u = [tx / tz, ty / tz];
    let u_clamped = [
        u[0].max(-cam.lim_x_neg).min(cam.lim_x_pos),
        u[1].max(-cam.lim_y_neg).min(cam.lim_y_pos),
    ];
    let txc = tz * u_clamped[0];
    let tyc = tz * u_clamped[1];
    let tz2 = tz * tz;
    let j = [
        cam.fx / tz,
        -cam.fx * txc / tz2,
        cam.fy / tz,
        -cam.fy * tyc / tz2,
    ];
    // J Sigma_c J^T with J = [[j0, 0, j1], [0, j2, j3]].
    let s = &sigma_c;
    let a = j[0] * (j[0] * s[0][0] + j[1] * s[2][0]) + j[1] * (j[0] * s[0][2] + j[1] * s[2][2]);
    let b = j[0] * (j[2] * s[0][1] + j[3] * s[0][2]) + j[1] * (j[2] * s[2][1] + j[3] * s[2][2]);
    let c = j[2] * (j[2] * s[1][1] + j[3] * s[2][1]) + j[3] * (j[2] * s[1][2] + j[3] * s[2][2]);
    let cov = [a + cam.eps2d, b, c + cam.eps2d];
    let det_raw = cov[0] * cov[2] - cov[1] * cov[1];
    // A clamp that keeps NaN (so that a NaN Gaussian is culled below, as in the reference).
    let det = if det_raw < T::lit(1e-10) {
        T::lit(1e-10)
    } else {
        det_raw
    };
    let conic = [cov[2] / det, -cov[1] / det, cov[0] / det];
    let mean2d = [cam.fx * tx / tz + cam.cx, cam.fy * ty / tz + cam.cy];
    Screen {
        p,
        sigma_c,
        u,
        u_clamped,
        j,
        cov,
        det_raw,
        det,
        mean2d,
        conic,
    }
}

#[inline(always)]
fn radii_of<T: Real>(cam: &CamT<T>, sc: &Screen<T>) -> [u32; 2] {
    let depth = sc.p[2];
    let valid = sc.det > T::zero() && depth > cam.near && depth < cam.far;
    if !valid {
        return [0, 0];
    }
    let rx = (cam.radius_sigma * sc.cov[0].sqrt()).ceil();
    let ry = (cam.radius_sigma * sc.cov[2].sqrt()).ceil();
    let [mx, my] = sc.mean2d;
    let inside =
        mx + rx > T::zero() && mx - rx < cam.width && my + ry > T::zero() && my - ry < cam.height;
    if !inside {
        return [0, 0];
    }
    // `as` saturates: a radius beyond u32::MAX pixels becomes u32::MAX.
    [rx.to_f64_exact() as u32, ry.to_f64_exact() as u32]
}

fn check_lengths(n: usize, quats: usize, log_scales: usize) {
    assert_eq!(quats, n, "project: {quats} quaternions for {n} means");
    assert_eq!(
        log_scales, n,
        "project: {log_scales} log-scales for {n} means"
    );
}

/// Below this many Gaussians per task, rayon's splitting overhead dominates.
const MIN_CHUNK: usize = 1024;

/// Projects Gaussians into `camera` (see the module documentation for the exact rules).
///
/// # Panics
/// If `quats` or `log_scales` differ in length from `means`.
pub fn project<T: Real>(
    camera: &Camera,
    means: &[[T; 3]],
    quats: &[[T; 4]],
    log_scales: &[[T; 3]],
    settings: &ProjectSettings,
) -> Projected<T> {
    let n = means.len();
    check_lengths(n, quats.len(), log_scales.len());
    let cam = CamT::<T>::new(camera, settings);
    // Every element is written once, by the loop below, instead of zeroed first and then
    // overwritten.
    let mut out = Projected {
        means2d: Vec::with_capacity(n),
        conics: Vec::with_capacity(n),
        depths: Vec::with_capacity(n),
        radii: Vec::with_capacity(n),
    };
    out.means2d.spare_capacity_mut()[..n]
        .par_chunks_mut(MIN_CHUNK)
        .zip(out.conics.spare_capacity_mut()[..n].par_chunks_mut(MIN_CHUNK))
        .zip(out.depths.spare_capacity_mut()[..n].par_chunks_mut(MIN_CHUNK))
        .zip(out.radii.spare_capacity_mut()[..n].par_chunks_mut(MIN_CHUNK))
        .enumerate()
        .for_each(|(c, (((means2d, conics), depths), radii))| {
            let r = c * MIN_CHUNK..c * MIN_CHUNK + means2d.len();
            in_isa::<T, _>(ForwardChunk {
                cam: &cam,
                means: &means[r.clone()],
                quats: &quats[r.clone()],
                log_scales: &log_scales[r],
                means2d,
                conics,
                depths,
                radii,
            });
        });
    // SAFETY: the chunks above cover the first `n` slots of the four buffers (the same
    // chunking of each), `ForwardChunk` writes every slot of its chunks, and `for_each`
    // returns only after every chunk is done.
    unsafe {
        out.means2d.set_len(n);
        out.conics.set_len(n);
        out.depths.set_len(n);
        out.radii.set_len(n);
    }
    out
}

/// Runs `op` compiled for the process's instruction set ([`base::isa`]) when `T` is `f32`
/// (the compiler vectorises its loop over Gaussians; IEEE operations give the same bits on
/// every instruction set, and no multiply-add is fused), as plain code otherwise.
#[inline(always)]
fn in_isa<T: Real, Op: pulp::WithSimd<Output = ()>>(op: Op) {
    if T::as_f32_slice(&[]).is_some() {
        base::isa::dispatch(op)
    } else {
        op.with_simd(pulp::Scalar::new())
    }
}

/// The projection of a run of Gaussians, one at a time: writes every slot of the outputs.
struct ForwardChunk<'a, T> {
    cam: &'a CamT<T>,
    means: &'a [[T; 3]],
    quats: &'a [[T; 4]],
    log_scales: &'a [[T; 3]],
    means2d: &'a mut [MaybeUninit<[T; 2]>],
    conics: &'a mut [MaybeUninit<[T; 3]>],
    depths: &'a mut [MaybeUninit<T>],
    radii: &'a mut [MaybeUninit<[u32; 2]>],
}

impl<T: Real> pulp::WithSimd for ForwardChunk<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let cam = self.cam;
        for i in 0..self.means.len() {
            let cov = covariance(&self.quats[i], &self.log_scales[i]);
            let sc = screen(cam, &self.means[i], &cov.sigma);
            self.means2d[i] = MaybeUninit::new(sc.mean2d);
            self.conics[i] = MaybeUninit::new(sc.conic);
            self.depths[i] = MaybeUninit::new(sc.p[2]);
            self.radii[i] = MaybeUninit::new(radii_of(cam, &sc));
        }
    }
}

/// The gradients of a run of Gaussians, one at a time, into every slot of the outputs; culled
/// ones get zero gradients.
struct BackwardChunk<'a, T> {
    cam: &'a CamT<T>,
    means: &'a [[T; 3]],
    quats: &'a [[T; 4]],
    log_scales: &'a [[T; 3]],
    radii: &'a [[u32; 2]],
    v_means2d: &'a [[T; 2]],
    v_conics: &'a [[T; 3]],
    v_depths: &'a [T],
    g_means: &'a mut [MaybeUninit<[T; 3]>],
    g_quats: &'a mut [MaybeUninit<[T; 4]>],
    g_log_scales: &'a mut [MaybeUninit<[T; 3]>],
}

impl<T: Real> pulp::WithSimd for BackwardChunk<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        // Every Gaussian is computed and the culled ones' results are replaced by zeros
        // (selects, not a branch around the stores), so that the loop vectorises across
        // Gaussians; a culled Gaussian's arithmetic may overflow, and is discarded.
        let zero = T::zero();
        for i in 0..self.means.len() {
            let culled = self.radii[i][0] == 0 || self.radii[i][1] == 0;
            let (gm, gq, gs) = backward_one(
                self.cam,
                &self.means[i],
                &self.quats[i],
                &self.log_scales[i],
                &self.v_means2d[i],
                &self.v_conics[i],
                self.v_depths[i],
            );
            self.g_means[i] = MaybeUninit::new(gm.map(|x| if culled { zero } else { x }));
            self.g_quats[i] = MaybeUninit::new(gq.map(|x| if culled { zero } else { x }));
            self.g_log_scales[i] = MaybeUninit::new(gs.map(|x| if culled { zero } else { x }));
        }
    }
}

/// Gradients of one Gaussian: `(d mean, d quat, d log_scale)`.
#[allow(clippy::type_complexity)]
#[inline(always)]
fn backward_one<T: Real>(
    cam: &CamT<T>,
    mean: &[T; 3],
    quat: &[T; 4],
    log_scale: &[T; 3],
    v_mean2d: &[T; 2],
    v_conic: &[T; 3],
    v_depth: T,
) -> ([T; 3], [T; 4], [T; 3]) {
    let zero = T::zero();
    let two = T::lit(2.0);
    let cov = covariance(quat, log_scale);
    let sc = screen(cam, mean, &cov.sigma);
    let [tx, ty, tz] = sc.p;
    let [a, b, c] = sc.cov;
    let det = sc.det;

    // conic = (c, -b, a) / det with det = max(a c - b^2, 1e-10).
    let [v_ca, v_cb, v_cc] = *v_conic;
    let g_det = if sc.det_raw >= T::lit(1e-10) {
        -(v_ca * c - v_cb * b + v_cc * a) / (det * det)
    } else {
        zero
    };
    let g_a = v_cc / det + g_det * c;
    let g_c = v_ca / det + g_det * a;
    let g_b = -v_cb / det - two * g_det * b;
    // Symmetric cotangent of cov2d (eps2d passes the gradient unchanged): b is both
    // off-diagonal entries, each carrying half of its gradient.
    let half = T::lit(0.5);
    let v = [[g_a, half * g_b], [half * g_b, g_c]];

    // cov2d = J Sigma_c J^T: dSigma_c = J^T V J, dJ = 2 V J Sigma_c.
    let [j00, j02, j11, j12] = sc.j;
    let jm = [[j00, zero, j02], [zero, j11, j12]];
    let vj: [[T; 3]; 2] = [
        v3(|k| v[0][0] * jm[0][k] + v[0][1] * jm[1][k]),
        v3(|k| v[1][0] * jm[0][k] + v[1][1] * jm[1][k]),
    ];
    let g_sigma_c: M3<T> = m3(|i, k| jm[0][i] * vj[0][k] + jm[1][i] * vj[1][k]);
    let s = &sc.sigma_c;
    let g_j =
        |r: usize, k: usize| two * (vj[r][0] * s[0][k] + vj[r][1] * s[1][k] + vj[r][2] * s[2][k]);
    let (g_j00, g_j02, g_j11, g_j12) = (g_j(0, 0), g_j(0, 2), g_j(1, 1), g_j(1, 2));

    // J entries: fx/z, -fx x'/z^2, fy/z, -fy y'/z^2 with x' = z clamp(x/z).
    let tz2 = tz * tz;
    let tz3 = tz2 * tz;
    let txc = tz * sc.u_clamped[0];
    let tyc = tz * sc.u_clamped[1];
    let mut g_tz = -cam.fx / tz2 * g_j00 - cam.fy / tz2 * g_j11
        + two * cam.fx * txc / tz3 * g_j02
        + two * cam.fy * tyc / tz3 * g_j12;
    let g_txc = -cam.fx / tz2 * g_j02;
    let g_tyc = -cam.fy / tz2 * g_j12;
    let mut g_tx = zero;
    let mut g_ty = zero;
    // x' = z clamp(u), u = x / z; the clamp passes the gradient where -lim_neg <= u <= lim_pos.
    g_tz += g_txc * sc.u_clamped[0] + g_tyc * sc.u_clamped[1];
    if sc.u[0] >= -cam.lim_x_neg && sc.u[0] <= cam.lim_x_pos {
        let g_u = g_txc * tz;
        g_tx += g_u / tz;
        g_tz -= g_u * tx / tz2;
    }
    if sc.u[1] >= -cam.lim_y_neg && sc.u[1] <= cam.lim_y_pos {
        let g_u = g_tyc * tz;
        g_ty += g_u / tz;
        g_tz -= g_u * ty / tz2;
    }

    // means2d = (fx x / z + cx, fy y / z + cy); depth = z.
    g_tx += v_mean2d[0] * cam.fx / tz;
    g_ty += v_mean2d[1] * cam.fy / tz;
    g_tz -= v_mean2d[0] * cam.fx * tx / tz2 + v_mean2d[1] * cam.fy * ty / tz2;
    g_tz += v_depth;

    // p = W m + t; Sigma_c = W Sigma W^T.
    let g_mean = matvec_t(&cam.rot, &[g_tx, g_ty, g_tz]);
    let g_sigma = matmul(&matmul(&transpose(&cam.rot), &g_sigma_c), &cam.rot);

    // Sigma = M M^T (g_sigma symmetric): dM = 2 dSigma M; M = R diag(s).
    let g_sigma_m = matmul(&g_sigma, &cov.m);
    let g_m = m3(|i, j| two * g_sigma_m[i][j]);
    let g_rot: M3<T> = m3(|i, j| g_m[i][j] * cov.scale[j]);
    let g_log_scale = v3(|j| {
        (g_m[0][j] * cov.rot[0][j] + g_m[1][j] * cov.rot[1][j] + g_m[2][j] * cov.rot[2][j])
            * cov.scale[j]
    });

    // R(q) for the unit quaternion q = (w, x, y, z).
    let [w, x, y, z] = cov.qn;
    let g = &g_rot;
    let g_qn = [
        two * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]),
        two * (y * g[0][1] + z * g[0][2] + y * g[1][0] - two * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - two * x * g[2][2]),
        two * (-two * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
            - w * g[2][0]
            + z * g[2][1]
            - two * y * g[2][2]),
        two * (-two * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - two * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]),
    ];
    // q_n = q / max(|q|, 1e-12): project out the radial part unless the norm was clamped.
    let g_quat = if !cov.norm_clamped {
        let qn = &cov.qn;
        let dot = qn[0] * g_qn[0] + qn[1] * g_qn[1] + qn[2] * g_qn[2] + qn[3] * g_qn[3];
        let d = cov.denom;
        [
            (g_qn[0] - qn[0] * dot) / d,
            (g_qn[1] - qn[1] * dot) / d,
            (g_qn[2] - qn[2] * dot) / d,
            (g_qn[3] - qn[3] * dot) / d,
        ]
    } else {
        let d = cov.denom;
        [g_qn[0] / d, g_qn[1] / d, g_qn[2] / d, g_qn[3] / d]
    };
    (g_mean, g_quat, g_log_scale)
}

/// The backward of [`project`]: given the cotangents of `means2d`, `conics` and `depths`, the
/// gradients with respect to `means`, `quats` (unnormalised) and `log_scales`. Gaussians that
/// `projected` marks as culled get zero gradient.
///
/// # Panics
/// If any input or cotangent differs in length from `means`.
#[allow(clippy::too_many_arguments)]
pub fn project_backward<T: Real>(
    camera: &Camera,
    means: &[[T; 3]],
    quats: &[[T; 4]],
    log_scales: &[[T; 3]],
    settings: &ProjectSettings,
    projected: &Projected<T>,
    v_means2d: &[[T; 2]],
    v_conics: &[[T; 3]],
    v_depths: &[T],
) -> ProjectionGrads<T> {
    let n = means.len();
    check_lengths(n, quats.len(), log_scales.len());
    assert_eq!(projected.radii.len(), n, "project_backward: radii length");
    assert_eq!(v_means2d.len(), n, "project_backward: v_means2d length");
    assert_eq!(v_conics.len(), n, "project_backward: v_conics length");
    assert_eq!(v_depths.len(), n, "project_backward: v_depths length");
    let cam = CamT::<T>::new(camera, settings);
    // Every element is written once, by the loop below, instead of zeroed first.
    let mut grads = ProjectionGrads {
        means: Vec::with_capacity(n),
        quats: Vec::with_capacity(n),
        log_scales: Vec::with_capacity(n),
    };
    grads.means.spare_capacity_mut()[..n]
        .par_chunks_mut(MIN_CHUNK)
        .zip(grads.quats.spare_capacity_mut()[..n].par_chunks_mut(MIN_CHUNK))
        .zip(grads.log_scales.spare_capacity_mut()[..n].par_chunks_mut(MIN_CHUNK))
        .enumerate()
        .for_each(|(c, ((g_means, g_quats), g_log_scales))| {
            let r = c * MIN_CHUNK..c * MIN_CHUNK + g_means.len();
            in_isa::<T, _>(BackwardChunk {
                cam: &cam,
                means: &means[r.clone()],
                quats: &quats[r.clone()],
                log_scales: &log_scales[r.clone()],
                radii: &projected.radii[r.clone()],
                v_means2d: &v_means2d[r.clone()],
                v_conics: &v_conics[r.clone()],
                v_depths: &v_depths[r],
                g_means,
                g_quats,
                g_log_scales,
            });
        });
    // SAFETY: the chunks above cover the first `n` slots of the three buffers (the same
    // chunking of each), `BackwardChunk` writes every slot of its chunks, and `for_each`
    // returns only after every chunk is done.
    unsafe {
        grads.means.set_len(n);
        grads.quats.set_len(n);
        grads.log_scales.set_len(n);
    }
    grads
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;

    /// A deterministic pseudo-random value in [-1, 1).
    fn noise(i: usize) -> f32 {
        let x = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        ((x >> 40) as f32 / (1u64 << 23) as f32) - 1.0
    }

    fn bits<const K: usize>(v: &[[f32; K]]) -> Vec<u32> {
        v.as_flattened().iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn the_vector_path_gives_the_bits_of_the_gaussian_by_gaussian_code() {
        // Several work items, a partial one, Gaussians behind the camera, off screen, tiny and
        // huge, and a zero quaternion (the clamped normalisation).
        let n = 2 * MIN_CHUNK + 37;
        let intrinsics = Intrinsics {
            fx: 60.0,
            fy: 62.0,
            cx: 31.0,
            cy: 25.0,
            width: 64,
            height: 48,
        };
        let camera = crate::camera_path::look_at(
            intrinsics,
            glam::DVec3::new(0.3, -0.2, -4.0),
            glam::DVec3::ZERO,
            glam::DVec3::Y,
        )
        .expect("a valid pose");
        let means: Vec<[f32; 3]> = (0..n)
            .map(|i| [0, 1, 2].map(|a| 5.0 * noise(3 * i + a)))
            .collect();
        let mut quats: Vec<[f32; 4]> = (0..n)
            .map(|i| [0, 1, 2, 3].map(|a| noise(7 * i + a + 1)))
            .collect();
        quats[n / 2] = [0.0; 4];
        let log_scales: Vec<[f32; 3]> = (0..n)
            .map(|i| [0, 1, 2].map(|a| 4.0 * noise(5 * i + a + 2) - 2.0))
            .collect();
        let settings = ProjectSettings::default();
        let p = project(&camera, &means, &quats, &log_scales, &settings);
        let visible = (0..n).filter(|&i| p.is_visible(i)).count();
        assert!(visible > n / 10 && visible < n, "{visible} of {n} visible");

        let cam = CamT::<f32>::new(&camera, &settings);
        let mut expected = (vec![[0f32; 2]; n], vec![[0f32; 3]; n], vec![[0f32; 1]; n]);
        let mut radii = vec![[0u32; 2]; n];
        for i in 0..n {
            let cov = covariance(&quats[i], &log_scales[i]);
            let sc = screen(&cam, &means[i], &cov.sigma);
            expected.0[i] = sc.mean2d;
            expected.1[i] = sc.conic;
            expected.2[i] = [sc.p[2]];
            radii[i] = radii_of(&cam, &sc);
        }
        let depths: Vec<[f32; 1]> = p.depths.iter().map(|&z| [z]).collect();
        assert_eq!(bits(&p.means2d), bits(&expected.0));
        assert_eq!(bits(&p.conics), bits(&expected.1));
        assert_eq!(bits(&depths), bits(&expected.2));
        assert_eq!(p.radii, radii);

        let v_means2d: Vec<[f32; 2]> = (0..n).map(|i| [noise(11 * i), noise(11 * i + 1)]).collect();
        let v_conics: Vec<[f32; 3]> = (0..n)
            .map(|i| [0, 1, 2].map(|a| noise(13 * i + a)))
            .collect();
        let v_depths: Vec<f32> = (0..n).map(|i| noise(17 * i)).collect();
        let g = project_backward(
            &camera,
            &means,
            &quats,
            &log_scales,
            &settings,
            &p,
            &v_means2d,
            &v_conics,
            &v_depths,
        );
        let mut e_means = vec![[0f32; 3]; n];
        let mut e_quats = vec![[0f32; 4]; n];
        let mut e_scales = vec![[0f32; 3]; n];
        for i in (0..n).filter(|&i| p.is_visible(i)) {
            (e_means[i], e_quats[i], e_scales[i]) = backward_one(
                &cam,
                &means[i],
                &quats[i],
                &log_scales[i],
                &v_means2d[i],
                &v_conics[i],
                v_depths[i],
            );
        }
        assert_eq!(bits(&g.means), bits(&e_means));
        assert_eq!(bits(&g.quats), bits(&e_quats));
        assert_eq!(bits(&g.log_scales), bits(&e_scales));
    }
}
