//! Forward behaviour of statistics, AdaIN variants, spatial control, colour preservation and the
//! style cache, checked against values derived by hand or by an independent formulation.

use ndarray::{s, Array2, Array4};
use style::*;

fn ramp(n: usize, c: usize, h: usize, w: usize, seed: u64) -> Array4<f64> {
    // Deterministic pseudo-random values in [-1, 1) (xorshift64*).
    let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    Array4::from_shape_fn((n, c, h, w), |_| {
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        let r = state.wrapping_mul(0x2545_f491_4f6c_dd1d);
        (r >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    })
}

fn max_abs_diff(a: &Array4<f64>, b: &Array4<f64>) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn channel_stats_are_the_unbiased_ones_with_eps() {
    let x = Array4::from_shape_vec(
        (1, 2, 2, 2),
        vec![1.0, 2.0, 3.0, 4.0, -1.0, -1.0, -1.0, -1.0],
    )
    .unwrap();
    let st = channel_stats(&x).unwrap();
    assert_eq!(st.mean[[0, 0]], 2.5);
    // sum of squared deviations 5, divided by m - 1 = 3.
    assert!((st.std[[0, 0]] - (5.0f64 / 3.0 + 1e-5).sqrt()).abs() < 1e-15);
    assert_eq!(st.mean[[0, 1]], -1.0);
    assert!((st.std[[0, 1]] - 1e-5f64.sqrt()).abs() < 1e-15);
}

#[test]
fn masked_stats_equal_the_stats_of_the_selected_pixels() {
    let x = ramp(2, 3, 5, 4, 1);
    let mask = Array2::from_shape_fn((5, 4), |(y, xx)| (y * 4 + xx) % 3 != 1);
    let picked: Vec<(usize, usize)> = mask
        .indexed_iter()
        .filter(|(_, &m)| m)
        .map(|(p, _)| p)
        .collect();
    let sub = Array4::from_shape_fn((2, 3, 1, picked.len()), |(n, c, _, k)| {
        x[[n, c, picked[k].0, picked[k].1]]
    });
    let a = masked_channel_stats(&x, mask.view()).unwrap();
    let b = channel_stats(&sub).unwrap();
    assert!((&a.mean - &b.mean).iter().all(|d| d.abs() < 1e-14));
    assert!((&a.std - &b.std).iter().all(|d| d.abs() < 1e-14));
}

#[test]
fn statistics_reject_degenerate_input() {
    let x = ramp(1, 2, 1, 1, 2);
    assert!(matches!(
        channel_stats(&x),
        Err(StyleError::TooFewPixels { count: 1, .. })
    ));
    let y = ramp(1, 2, 3, 3, 2);
    let one = Array2::from_shape_fn((3, 3), |(a, b)| a == 0 && b == 0);
    assert!(masked_channel_stats(&y, one.view()).is_err());
    let wrong = Array2::from_elem((2, 3), true);
    assert!(matches!(
        masked_channel_stats(&y, wrong.view()),
        Err(StyleError::Shape { .. })
    ));
}

#[test]
fn adain_moves_the_content_to_the_style_mean_and_keeps_structure() {
    let c = ramp(1, 4, 6, 5, 3);
    let s = ramp(1, 4, 7, 3, 4).mapv(|v| 3.0 * v + 0.5);
    let out = adain(&c, &s).unwrap();
    let (so, ss) = (channel_stats(&out).unwrap(), channel_stats(&s).unwrap());
    // Means match exactly; stds match up to the eps inside the content's normalisation:
    // std(out) = std_s * sqrt(var_c / (var_c + eps) + eps / std_s^2) in the variance sense.
    for j in 0..4 {
        assert!((so.mean[[0, j]] - ss.mean[[0, j]]).abs() < 1e-12);
        assert!((so.std[[0, j]] / ss.std[[0, j]] - 1.0).abs() < 1e-4);
    }
    // A style with the content's own statistics gives the content back.
    let same = adain_with_stats(&c, &channel_stats(&c).unwrap()).unwrap();
    assert!(max_abs_diff(&same, &c) < 1e-12);
}

#[test]
fn alpha_and_mix_are_the_stated_combinations() {
    let c = ramp(1, 3, 4, 4, 5);
    let s1 = channel_stats(&ramp(1, 3, 5, 5, 6).mapv(|v| 2.0 * v + 1.0)).unwrap();
    let s2 = channel_stats(&ramp(1, 3, 3, 6, 7).mapv(|v| 0.5 * v - 1.0)).unwrap();
    let a1 = adain_with_stats(&c, &s1).unwrap();
    let a2 = adain_with_stats(&c, &s2).unwrap();
    assert!(max_abs_diff(&adain_alpha(&c, &s1, 1.0).unwrap(), &a1) < 1e-15);
    assert!(max_abs_diff(&adain_alpha(&c, &s1, 0.0).unwrap(), &c) < 1e-15);
    let expect_alpha = &a1 * 0.6 + &c * 0.4;
    assert!(max_abs_diff(&adain_alpha(&c, &s1, 0.6).unwrap(), &expect_alpha) < 1e-14);
    let expect_mix = &a1 * 0.3 + &a2 * 0.7;
    assert!(
        max_abs_diff(
            &adain_mix(&c, &[(&s1, 0.3), (&s2, 0.7)]).unwrap(),
            &expect_mix
        ) < 1e-14
    );
    assert!(adain_mix::<f64>(&c, &[]).is_err());
    assert!(adain_alpha(&c, &s1, f64::NAN).is_err());
}

#[test]
fn style_statistics_broadcast_over_a_batch_and_check_channels() {
    let c = ramp(3, 2, 4, 4, 8);
    let s = channel_stats(&ramp(1, 2, 4, 4, 9)).unwrap();
    let batch = adain_with_stats(&c, &s).unwrap();
    for n in 0..3 {
        let one = c.slice(s![n..n + 1, .., .., ..]).to_owned();
        let single = adain_with_stats(&one, &s).unwrap();
        assert!(max_abs_diff(&batch.slice(s![n..n + 1, .., .., ..]).to_owned(), &single) < 1e-15);
    }
    let wrong = channel_stats(&ramp(1, 3, 4, 4, 9)).unwrap();
    assert!(matches!(
        adain_with_stats(&c, &wrong),
        Err(StyleError::Shape { .. })
    ));
}

#[test]
fn spatial_control_styles_each_region_with_its_own_style() {
    let c = ramp(1, 3, 6, 6, 10);
    let sa = channel_stats(&ramp(1, 3, 4, 4, 11).mapv(|v| v + 2.0)).unwrap();
    let sb = channel_stats(&ramp(1, 3, 4, 4, 12).mapv(|v| 3.0 * v - 2.0)).unwrap();
    // One region covering everything is plain AdaIN.
    let all = Array2::from_elem((6, 6), true);
    let whole = adain_spatial(
        &c,
        &[Region {
            mask: all.view(),
            style: &sa,
        }],
    )
    .unwrap();
    assert!(max_abs_diff(&whole, &adain_with_stats(&c, &sa).unwrap()) < 1e-14);
    // Left half style a, top-right quarter style b, bottom-right untouched.
    let left = Array2::from_shape_fn((6, 6), |(_, x)| x < 3);
    let top_right = Array2::from_shape_fn((6, 6), |(y, x)| x >= 3 && y < 3);
    let out = adain_spatial(
        &c,
        &[
            Region {
                mask: left.view(),
                style: &sa,
            },
            Region {
                mask: top_right.view(),
                style: &sb,
            },
        ],
    )
    .unwrap();
    let expect_left = adain_with_stats(&c.slice(s![.., .., .., 0..3]).to_owned(), &sa).unwrap();
    let expect_tr = adain_with_stats(&c.slice(s![.., .., 0..3, 3..6]).to_owned(), &sb).unwrap();
    assert!(max_abs_diff(&out.slice(s![.., .., .., 0..3]).to_owned(), &expect_left) < 1e-14);
    assert!(max_abs_diff(&out.slice(s![.., .., 0..3, 3..6]).to_owned(), &expect_tr) < 1e-14);
    assert_eq!(
        out.slice(s![.., .., 3..6, 3..6]),
        c.slice(s![.., .., 3..6, 3..6])
    );
    // Overlapping regions are an error.
    let overlap = adain_spatial(
        &c,
        &[
            Region {
                mask: left.view(),
                style: &sa,
            },
            Region {
                mask: all.view(),
                style: &sb,
            },
        ],
    );
    assert!(matches!(overlap, Err(StyleError::Invalid { .. })));
}

#[test]
fn mask_resize_is_nearest() {
    let m = Array2::from_shape_fn((4, 4), |(y, x)| y < 2 && x >= 2);
    let r = resize_mask_nearest(m.view(), 2, 2).unwrap();
    assert_eq!(
        r,
        Array2::from_shape_vec((2, 2), vec![false, true, false, false]).unwrap()
    );
    let up = resize_mask_nearest(r.view(), 4, 4).unwrap();
    assert_eq!(up, m);
}

fn rgb_mean_cov(img: &Array4<f64>) -> ([f64; 3], [[f64; 3]; 3]) {
    let (_, _, h, w) = img.dim();
    let m = (h * w) as f64;
    let mu = [0, 1, 2].map(|c| img.slice(s![0, c, .., ..]).sum() / m);
    let mut cov = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let a = img.slice(s![0, i, .., ..]).mapv(|v| v - mu[i]);
            let b = img.slice(s![0, j, .., ..]).mapv(|v| v - mu[j]);
            cov[i][j] = (&a * &b).sum() / (m - 1.0);
        }
    }
    (mu, cov)
}

#[test]
fn colour_preservation_gives_the_style_the_content_colour_moments() {
    // Correlated colours in both images.
    let base_c = ramp(1, 3, 9, 8, 13).mapv(|v| 0.5 + 0.3 * v);
    let mut content = base_c.clone();
    content
        .slice_mut(s![0, 1, .., ..])
        .scaled_add(0.5, &base_c.slice(s![0, 0, .., ..]));
    let base_s = ramp(1, 3, 7, 10, 14).mapv(|v| 0.4 + 0.2 * v);
    let mut style_img = base_s.clone();
    style_img
        .slice_mut(s![0, 2, .., ..])
        .scaled_add(-0.8, &base_s.slice(s![0, 1, .., ..]));
    let out = preserve_colour_with_eps(&style_img, &content, 0.0).unwrap();
    let (mo, co) = rgb_mean_cov(&out);
    let (mc, cc) = rgb_mean_cov(&content);
    for i in 0..3 {
        assert!((mo[i] - mc[i]).abs() < 1e-12);
        for j in 0..3 {
            assert!(
                (co[i][j] - cc[i][j]).abs() < 1e-12,
                "cov {i}{j}: {} vs {}",
                co[i][j],
                cc[i][j]
            );
        }
    }
    assert_eq!(out.dim(), style_img.dim());
    // A flat grey style stays well defined thanks to the ridge (and becomes the content mean).
    let flat = Array4::from_elem((1, 3, 4, 4), 0.5);
    let out_flat = preserve_colour(&flat, &content).unwrap();
    for (c, mean) in mc.iter().enumerate() {
        assert!(out_flat
            .slice(s![0, c, .., ..])
            .iter()
            .all(|v| (v - mean).abs() < 1e-12));
    }
    assert!(preserve_colour(&ramp(1, 4, 3, 3, 1), &content).is_err());
}

#[test]
fn style_cache_computes_each_style_once() {
    let cache = StyleCache::<f32>::new();
    let img = ramp(1, 3, 8, 8, 15).mapv(|v| v as f32);
    let feats = [img.clone(), img.mapv(|v| 2.0 * v)];
    let mut computed = 0;
    let key = StyleKey::from_image("vgg-fullres", &img);
    for _ in 0..3 {
        let st = cache
            .get_or_compute(&key, || {
                computed += 1;
                StyleFeatureStats::from_features(&feats)
            })
            .unwrap();
        assert_eq!(st.levels.len(), 2);
        assert_eq!(st.deepest(), &channel_stats(&feats[1]).unwrap());
    }
    assert_eq!(computed, 1);
    assert_eq!(cache.counts(), (2, 1));
    // Same pixels from another array are the same key; other pixels or another encoder are not.
    assert_eq!(StyleKey::from_image("vgg-fullres", &img.clone()), key);
    let mut other = img.clone();
    other[[0, 0, 0, 0]] += 1e-3;
    assert_ne!(StyleKey::from_image("vgg-fullres", &other), key);
    assert_ne!(StyleKey::from_image("vgg-standard", &img), key);
    assert_ne!(
        StyleKey::from_path("vgg-fullres", std::path::Path::new("a.jpg")),
        key
    );
    // A failed computation is reported and nothing is cached.
    let bad = StyleKey::from_path("vgg-fullres", std::path::Path::new("b.jpg"));
    assert!(cache
        .get_or_compute(&bad, || StyleFeatureStats::from_features(&[]))
        .is_err());
    assert_eq!(cache.len(), 1);
}
