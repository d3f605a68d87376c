//! Every backward pass against central differences, in `f64`, on random inputs (proptest).
//!
//! Each check contracts the output with a random cotangent `v`, giving the scalar
//! `L(x) = sum(v * f(x))`, and compares the analytic gradient with
//! `(L(x + h e_k) - L(x - h e_k)) / (2h)` for every input element `k`, with `h = 1e-6`.
//! Truncation error is `O(h^2) ~ 1e-12` times third derivatives of order one here, and the
//! rounding error is about `1e-16 * |L| / h ~ 1e-9`; the tolerance `GRAD_TOL = 1e-6` (relative,
//! infinity norm) is well above both and far below any real mistake (wrong factors are >= 1e-2).
//!
//! Smoothness: the statistics are smooth (eps 1e-5 keeps the std away from zero, and inputs of at
//! least two distinct values give a positive variance anyway); the only kink is `|a - b|` in the
//! L1 loss, which is avoided by keeping every `|a_k - b_k| >= 0.05`, far beyond `h`.

use dsgs_testkit::max_rel_err;
use ndarray::{Array2, Array4};
use proptest::prelude::*;
use style::*;

const H: f64 = 1e-6;
const GRAD_TOL: f64 = 1e-6;

fn numeric_grad(x: &Array4<f64>, f: impl Fn(&Array4<f64>) -> f64) -> Array4<f64> {
    let mut g = Array4::zeros(x.raw_dim());
    let mut xp = x.clone();
    for (idx, gv) in g.indexed_iter_mut() {
        let orig = xp[idx];
        xp[idx] = orig + H;
        let lp = f(&xp);
        xp[idx] = orig - H;
        let lm = f(&xp);
        xp[idx] = orig;
        *gv = (lp - lm) / (2.0 * H);
    }
    g
}

fn dot(a: &Array4<f64>, b: &Array4<f64>) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn check(what: &str, analytic: &Array4<f64>, numeric: &Array4<f64>) -> Result<(), TestCaseError> {
    let err = max_rel_err(analytic.as_slice().unwrap(), numeric.as_slice().unwrap());
    prop_assert!(err <= GRAD_TOL, "{what}: relative error {err:.3e}");
    Ok(())
}

/// A random `[n, c, h, w]` map with entries in `[-2, 2]`.
fn map(n: usize, c: usize, h: usize, w: usize) -> impl Strategy<Value = Array4<f64>> {
    prop::collection::vec(-2.0f64..2.0, n * c * h * w)
        .prop_map(move |v| Array4::from_shape_vec((n, c, h, w), v).unwrap())
}

fn dims() -> impl Strategy<Value = (usize, usize, usize, usize)> {
    (1usize..3, 1usize..4, 2usize..5, 2usize..5)
}

/// Two maps of the same random shape.
fn pair() -> impl Strategy<Value = (Array4<f64>, Array4<f64>)> {
    dims().prop_flat_map(|(n, c, h, w)| (map(n, c, h, w), map(n, c, h, w)))
}

/// A map, a cotangent of its shape and random `[1, c]` style statistics (std in [0.2, 3]).
fn map_cot_style() -> impl Strategy<Value = (Array4<f64>, Array4<f64>, ChannelStats<f64>)> {
    dims().prop_flat_map(|(n, c, h, w)| {
        (
            map(n, c, h, w),
            map(n, c, h, w),
            prop::collection::vec(-2.0f64..2.0, c),
            prop::collection::vec(0.2f64..3.0, c),
        )
            .prop_map(move |(x, v, m, s)| {
                let st = ChannelStats::new(
                    Array2::from_shape_vec((1, c), m).unwrap(),
                    Array2::from_shape_vec((1, c), s).unwrap(),
                )
                .unwrap();
                (x, v, st)
            })
    })
}

/// A mask with at least two pixels set.
fn mask_for(h: usize, w: usize, bits: &[bool]) -> Array2<bool> {
    let mut m = Array2::from_shape_vec((h, w), bits.to_vec()).unwrap();
    m[[0, 0]] = true;
    m[[h - 1, w - 1]] = true;
    m
}

fn stats_dot(a: &ChannelStats<f64>, b: &ChannelStats<f64>) -> f64 {
    a.mean.iter().zip(&b.mean).map(|(x, y)| x * y).sum::<f64>()
        + a.std.iter().zip(&b.std).map(|(x, y)| x * y).sum::<f64>()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn channel_stats_backward_matches_differences((x, _) in pair(), seed in 0u64..1000) {
        let (n, c, _, _) = x.dim();
        let cot = ChannelStats::new(
            Array2::from_shape_fn((n, c), |(i, j)| ((i * 7 + j * 3 + seed as usize) % 5) as f64 - 2.0),
            Array2::from_shape_fn((n, c), |(i, j)| ((i * 5 + j + seed as usize) % 7) as f64 - 3.0),
        ).unwrap();
        let stats = channel_stats(&x).unwrap();
        let analytic = channel_stats_backward(&x, &stats, &cot).unwrap();
        let numeric = numeric_grad(&x, |x| stats_dot(&channel_stats(x).unwrap(), &cot));
        check("channel_stats", &analytic, &numeric)?;
    }

    #[test]
    fn masked_channel_stats_backward_matches_differences(
        (x, bits) in dims().prop_flat_map(|(n, c, h, w)| (map(n, c, h, w), prop::collection::vec(any::<bool>(), h * w)))
    ) {
        let (n, c, h, w) = x.dim();
        let mask = mask_for(h, w, &bits);
        let cot = ChannelStats::new(
            Array2::from_shape_fn((n, c), |(i, j)| 1.0 + i as f64 - 0.5 * j as f64),
            Array2::from_shape_fn((n, c), |(i, j)| -0.7 + 0.3 * (i + j) as f64),
        ).unwrap();
        let stats = masked_channel_stats(&x, mask.view()).unwrap();
        let analytic = masked_channel_stats_backward(&x, mask.view(), &stats, &cot).unwrap();
        let numeric = numeric_grad(&x, |x| stats_dot(&masked_channel_stats(x, mask.view()).unwrap(), &cot));
        check("masked channel_stats", &analytic, &numeric)?;
    }

    #[test]
    fn instance_normalize_backward_matches_differences((x, v) in pair()) {
        let analytic = instance_normalize_backward(&x, &v).unwrap();
        let numeric = numeric_grad(&x, |x| dot(&instance_normalize(x).unwrap(), &v));
        check("instance_normalize", &analytic, &numeric)?;
    }

    #[test]
    fn style_transform_backward_matches_differences((y, v, style) in map_cot_style()) {
        let (g_y, g_style) = style_transform_backward(&y, &style, &v).unwrap();
        let numeric = numeric_grad(&y, |y| dot(&style_transform(y, &style).unwrap(), &v));
        check("style_transform input", &g_y, &numeric)?;
        // The statistics' gradient: perturb the style mean and std one channel at a time.
        for j in 0..style.channels() {
            for which in 0..2 {
                let f = |d: f64| {
                    let mut s = style.clone();
                    if which == 0 { s.mean[[0, j]] += d } else { s.std[[0, j]] += d }
                    dot(&style_transform(&y, &s).unwrap(), &v)
                };
                let num = (f(H) - f(-H)) / (2.0 * H);
                let ana = if which == 0 { g_style.mean[[0, j]] } else { g_style.std[[0, j]] };
                prop_assert!((num - ana).abs() <= GRAD_TOL * num.abs().max(1.0), "style stat {which} {j}: {ana} vs {num}");
            }
        }
    }

    #[test]
    fn adain_backward_matches_differences(
        (c, v, s) in dims().prop_flat_map(|(n, c, h, w)| (map(n, c, h, w), map(n, c, h, w), map(1, c, h + 1, w)))
    ) {
        // Through the content and, via channel_stats_backward, through the style features.
        let stats = channel_stats(&s).unwrap();
        let (g_c, g_stats) = adain_backward(&c, &stats, &v).unwrap();
        let g_s = channel_stats_backward(&s, &stats, &g_stats).unwrap();
        let num_c = numeric_grad(&c, |c| dot(&adain(c, &s).unwrap(), &v));
        let num_s = numeric_grad(&s, |s| dot(&adain(&c, s).unwrap(), &v));
        check("adain content", &g_c, &num_c)?;
        check("adain style", &g_s, &num_s)?;
    }

    #[test]
    fn adain_spatial_backward_matches_differences(
        (x, v, bits, style_a, style_b) in (1usize..3, 1usize..4, 3usize..6, 3usize..6).prop_flat_map(|(n, c, h, w)| (
            map(n, c, h, w), map(n, c, h, w), prop::collection::vec(0u8..3, h * w),
            map(1, c, 3, 3), map(1, c, 2, 4)))
    ) {
        let (_, _, h, w) = x.dim();
        // Region 0 where bits == 0, region 1 where bits == 1, unstyled where bits == 2. Each
        // region gets at least three pixels: with exactly two, normalisation maps them to about
        // +-1/sqrt(2) whatever their values, the gradient is of order eps and a relative
        // comparison with differences would measure only rounding noise.
        let mut owner = Array2::from_shape_vec((h, w), bits).unwrap();
        for k in 0..3 {
            owner[[0, k]] = 0;
            owner[[h - 1, k]] = 1;
        }
        let m0 = owner.mapv(|o| o == 0);
        let m1 = owner.mapv(|o| o == 1);
        let (sa, sb) = (channel_stats(&style_a).unwrap(), channel_stats(&style_b).unwrap());
        let regions = [Region { mask: m0.view(), style: &sa }, Region { mask: m1.view(), style: &sb }];
        let analytic = adain_spatial_backward(&x, &regions, &v).unwrap();
        let numeric = numeric_grad(&x, |x| dot(&adain_spatial(x, &regions).unwrap(), &v));
        check("adain_spatial", &analytic, &numeric)?;
    }

    #[test]
    fn mse_and_content_backward_match_differences((a, b) in pair(), g in 0.1f64..3.0) {
        let ga = mse_backward(&a, &b, g).unwrap();
        check("mse a", &ga, &numeric_grad(&a, |a| g * mse(a, &b).unwrap()))?;
        check("mse b", &ga.mapv(|v| -v), &numeric_grad(&b, |b| g * mse(&a, b).unwrap()))?;
        let gc = content_loss_backward(&a, &b, g).unwrap();
        check("content", &gc, &numeric_grad(&a, |a| g * content_loss(a, &b).unwrap()))?;
        let gal = align_loss_backward(&a, &b, AlignLoss::Mse, g).unwrap();
        check("align mse", &gal, &numeric_grad(&a, |a| g * align_loss(a, &b, AlignLoss::Mse).unwrap()))?;
    }

    #[test]
    fn l1_backward_matches_differences((a, b) in pair(), g in 0.1f64..3.0) {
        // Keep every |a - b| >= 0.05 so that no central difference straddles the kink.
        let a = ndarray::Zip::from(&a).and(&b).map_collect(|&x, &y| {
            if (x - y).abs() < 0.05 { y + 0.05f64.copysign(x - y + 1e-300) } else { x }
        });
        let ga = l1_backward(&a, &b, g).unwrap();
        check("l1", &ga, &numeric_grad(&a, |a| g * l1(a, &b).unwrap()))?;
        let gal = align_loss_backward(&a, &b, AlignLoss::L1, g).unwrap();
        check("align l1", &gal, &numeric_grad(&a, |a| g * align_loss(a, &b, AlignLoss::L1).unwrap()))?;
    }

    #[test]
    fn style_loss_backward_matches_differences(
        (gen0, gen1, s0, s1) in (1usize..3, 1usize..4, 2usize..5).prop_flat_map(|(n, c, h)| (
            map(n, c, h, h + 1), map(n, c + 1, h, 2), map(1, c, 3, 2), map(n, c + 1, 2, 3)))
    ) {
        // Two levels; the first level's style broadcasts over the batch, the second does not.
        let style = vec![channel_stats(&s0).unwrap(), channel_stats(&s1).unwrap()];
        let g = 1.7;
        let grads = style_loss_backward(&[gen0.clone(), gen1.clone()], &style, g).unwrap();
        let n0 = numeric_grad(&gen0, |x| g * style_loss(&[x.clone(), gen1.clone()], &style).unwrap());
        let n1 = numeric_grad(&gen1, |x| g * style_loss(&[gen0.clone(), x.clone()], &style).unwrap());
        check("style level 0", &grads[0], &n0)?;
        check("style level 1", &grads[1], &n1)?;
    }
}
