//! Initial Gaussians from a point cloud, as the 3DGS trainer builds them (`create_from_pcd`).
//!
//! For every point: the mean is the point; the three log-scales are all
//! `ln(sqrt(d2))`, where `d2` is the mean squared distance to the point's 3 nearest other points,
//! clamped below at 1e-7 (3DGS's `distCUDA2`, computed here exactly with a k-d tree); the rotation
//! is the identity quaternion `(1, 0, 0, 0)`; the opacity logit is `logit(0.1)`; the SH DC
//! coefficient is `(rgb - 0.5) / C0` with `C0 = 0.28209479177387814`, and every higher SH
//! coefficient is zero.
//!
//! [`random_points_in_box`] reproduces the NeRF-synthetic initialisation of 3DGS: 100,000 points
//! uniform in `[-1.3, 1.3]^3`, whose colours are `SH2RGB(u / 255)` for `u` uniform in [0, 1)
//! (so the DC coefficients start uniform in [0, 1/255), i.e. colours barely above mid-grey).

use gaussian::FeatureGaussians;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use std::num::NonZeroUsize;

use crate::error::TrainError;

/// The degree-0 real SH basis constant, `1 / (2 sqrt(pi))`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// Lower clamp of the mean squared neighbour distance (3DGS: `clamp_min(dist2, 1e-7)`).
pub const MIN_NEIGHBOUR_DIST2: f64 = 1e-7;
/// Initial opacity of every Gaussian.
pub const INITIAL_OPACITY: f64 = 0.1;
/// Neighbours averaged for the initial scale.
pub const SCALE_NEIGHBOURS: usize = 3;

/// A coloured point cloud: positions and RGB colours in [0, 1].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// Point positions, one `[x, y, z]` per point.
    pub positions: Vec<[f32; 3]>,
    /// RGB colour of each point, in [0, 1]; as long as `positions`.
    pub colors: Vec<[f32; 3]>,
}

/// `log(p / (1 - p))`.
pub fn inverse_sigmoid(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

/// RGB to the SH DC coefficient: `(rgb - 0.5) / C0`.
pub fn rgb_to_sh_dc(rgb: f64) -> f64 {
    (rgb - 0.5) / SH_C0
}

/// SH DC coefficient to RGB: `dc * C0 + 0.5`.
pub fn sh_dc_to_rgb(dc: f64) -> f64 {
    dc * SH_C0 + 0.5
}

/// `n` points uniform in the axis-aligned box `[lo, hi]` with the 3DGS random colours
/// (`SH2RGB(u / 255)`), from a seeded generator.
pub fn random_points_in_box(n: usize, lo: [f64; 3], hi: [f64; 3], seed: u64) -> PointCloud {
    let mut rng = StdRng::seed_from_u64(seed);
    let positions = (0..n)
        .map(|_| std::array::from_fn(|a| (lo[a] + rng.random::<f64>() * (hi[a] - lo[a])) as f32))
        .collect();
    let colors = (0..n)
        .map(|_| std::array::from_fn(|_| sh_dc_to_rgb(rng.random::<f64>() / 255.0) as f32))
        .collect();
    PointCloud { positions, colors }
}

/// For every point, the mean squared distance to its `SCALE_NEIGHBOURS` nearest other points,
/// clamped below at [`MIN_NEIGHBOUR_DIST2`]. With fewer points, the mean runs over all the others
/// (a single point gets the clamp value). Fails on non-finite coordinates.
pub fn mean_neighbour_dist2(points: &[[f32; 3]]) -> Result<Vec<f64>, TrainError> {
    if let Some(i) = points.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
        return Err(TrainError::Shape(format!(
            "point {i} of the initial point cloud is not finite: {:?}",
            points[i]
        )));
    }
    let pts: Vec<[f64; 3]> = points.iter().map(|p| p.map(f64::from)).collect();
    if pts.len() < 2 {
        return Ok(vec![MIN_NEIGHBOUR_DIST2; pts.len()]);
    }
    let tree: ImmutableKdTree<f64, 3> =
        ImmutableKdTree::new_from_slice(&pts).map_err(TrainError::PointIndex)?;
    let k = (SCALE_NEIGHBOURS + 1).min(pts.len());
    let k = NonZeroUsize::new(k).expect("at least two points");
    Ok(pts
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let found = tree
                .query(p)
                .nearest_n::<SquaredEuclidean<f64>>(k)
                .execute();
            // drop the query point itself; with duplicates it may be absent, and then the first
            // neighbours are the duplicates at distance 0, which is what we want.
            let dists: Vec<f64> = found
                .iter()
                .filter(|r| r.item as usize != i)
                .map(|r| r.distance)
                .take(SCALE_NEIGHBOURS)
                .collect();
            let mean = dists.iter().sum::<f64>() / dists.len() as f64;
            mean.max(MIN_NEIGHBOUR_DIST2)
        })
        .collect())
}

/// Initial Gaussians from a point cloud, with SH coefficients allocated up to `sh_degree` (the
/// maximum degree training will reach; coefficients above DC start at zero).
pub fn gaussians_from_points(
    cloud: &PointCloud,
    sh_degree: usize,
) -> Result<FeatureGaussians<f32>, TrainError> {
    if cloud.positions.len() != cloud.colors.len() {
        return Err(TrainError::Shape(format!(
            "point cloud has {} positions but {} colours",
            cloud.positions.len(),
            cloud.colors.len()
        )));
    }
    if cloud.positions.is_empty() {
        return Err(TrainError::Dataset(
            "the initial point cloud is empty".to_string(),
        ));
    }
    if sh_degree > 3 {
        return Err(TrainError::Config(format!(
            "SH degree {sh_degree} is above the supported maximum 3"
        )));
    }
    let d2 = mean_neighbour_dist2(&cloud.positions)?;
    let k = (sh_degree + 1) * (sh_degree + 1);
    let n = cloud.positions.len();
    let mut sh = vec![[0.0f32; 3]; n * k];
    for (i, c) in cloud.colors.iter().enumerate() {
        sh[i * k] = c.map(|v| rgb_to_sh_dc(v as f64) as f32);
    }
    let opacity_logit = inverse_sigmoid(INITIAL_OPACITY) as f32;
    Ok(FeatureGaussians {
        means: cloud.positions.clone(),
        log_scales: d2.iter().map(|&d| [(d.sqrt().ln()) as f32; 3]).collect(),
        quats: vec![[1.0, 0.0, 0.0, 0.0]; n],
        opacity_logits: vec![opacity_logit; n],
        sh_degree,
        sh,
        feature_dim: 0,
        features: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute-force reference for the neighbour distances.
    fn brute_force(points: &[[f32; 3]]) -> Vec<f64> {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut d: Vec<f64> = points
                    .iter()
                    .enumerate()
                    .filter(|&(j, _)| j != i)
                    .map(|(_, q)| (0..3).map(|a| (p[a] as f64 - q[a] as f64).powi(2)).sum())
                    .collect();
                d.sort_by(f64::total_cmp);
                let m = d.len().min(3);
                (d[..m].iter().sum::<f64>() / m as f64).max(MIN_NEIGHBOUR_DIST2)
            })
            .collect()
    }

    #[test]
    fn neighbour_distances_match_brute_force() {
        let cloud = random_points_in_box(2000, [-1.0, -2.0, 0.0], [1.0, 0.5, 3.0], 5);
        let mut pts = cloud.positions.clone();
        // duplicates and a tight cluster exercise the clamp and the self-exclusion
        pts.push(pts[0]);
        pts.push(pts[0]);
        pts.push(pts[0]);
        pts.push(pts[0]);
        let fast = mean_neighbour_dist2(&pts).unwrap();
        let slow = brute_force(&pts);
        for (a, b) in fast.iter().zip(&slow) {
            assert!((a - b).abs() <= 1e-12 * b.max(1e-7), "{a} vs {b}");
        }
        assert_eq!(fast[0], MIN_NEIGHBOUR_DIST2);
    }

    #[test]
    fn tiny_clouds_and_bad_points() {
        assert_eq!(
            mean_neighbour_dist2(&[[0.0, 0.0, 0.0]]).unwrap(),
            vec![MIN_NEIGHBOUR_DIST2]
        );
        let two = mean_neighbour_dist2(&[[0.0, 0.0, 0.0], [0.0, 3.0, 4.0]]).unwrap();
        assert_eq!(two, vec![25.0, 25.0]);
        assert!(mean_neighbour_dist2(&[[0.0, f32::NAN, 0.0], [1.0, 1.0, 1.0]]).is_err());
    }

    #[test]
    fn initial_gaussians_follow_3dgs() {
        // four points on a unit square: each point's 3 nearest neighbours are at squared
        // distances 1, 1 and 2, so d2 = 4/3 and the log-scale is ln(sqrt(4/3)).
        let cloud = PointCloud {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0],
            ],
            colors: vec![[0.5, 0.0, 1.0]; 4],
        };
        let g = gaussians_from_points(&cloud, 3).unwrap();
        assert_eq!(g.len(), 4);
        assert_eq!(g.sh.len(), 4 * 16);
        let expected_log_scale = (4.0f64 / 3.0).sqrt().ln() as f32;
        for i in 0..4 {
            assert_eq!(g.log_scales[i], [expected_log_scale; 3]);
            assert_eq!(g.quats[i], [1.0, 0.0, 0.0, 0.0]);
            assert!((1.0 / (1.0 + (-g.opacity_logits[i] as f64).exp()) - 0.1).abs() < 1e-7);
            let dc = g.sh[i * 16];
            assert_eq!(dc[0], 0.0);
            assert!((dc[1] as f64 - (-0.5 / 0.282_094_791_773_878_14)).abs() < 1e-6);
            assert!((dc[2] as f64 - (0.5 / 0.282_094_791_773_878_14)).abs() < 1e-6);
            assert!(g.sh[i * 16 + 1..(i + 1) * 16]
                .iter()
                .all(|c| *c == [0.0; 3]));
        }
        assert!(gaussians_from_points(&PointCloud::default(), 3).is_err());
        assert!(gaussians_from_points(&cloud, 4).is_err());
    }

    #[test]
    fn random_cloud_is_reproducible_and_in_the_box() {
        let a = random_points_in_box(1000, [-1.3; 3], [1.3; 3], 42);
        let b = random_points_in_box(1000, [-1.3; 3], [1.3; 3], 42);
        assert_eq!(a, b);
        assert!(a
            .positions
            .iter()
            .all(|p| p.iter().all(|&v| (-1.3..=1.3).contains(&v))));
        // colours SH2RGB(u / 255): within [0.5, 0.5 + C0 / 255)
        assert!(a.colors.iter().all(|c| c
            .iter()
            .all(|&v| v >= 0.5 && (v as f64) < 0.5 + SH_C0 / 255.0 + 1e-7)));
    }
}
