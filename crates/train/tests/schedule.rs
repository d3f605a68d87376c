//! `GeometryConfig::scaled_to`: the geometry schedule stretched or compressed to another run
//! length. Properties of the rule, checked over many lengths and several schedules: identity at
//! the configured length, every event within the run, events in their order, intervals of at
//! least one step, the floors of the shortened density intervals, and a round trip that restores
//! the schedule within rounding.

use train::density::{MIN_DENSIFICATION_INTERVAL, MIN_OPACITY_RESET_INTERVAL};
use train::{DensifyConfig, GeometryConfig};

/// Run lengths from a single step to three times the 3DGS length.
const LENGTHS: [u64; 16] = [
    1, 2, 3, 7, 10, 33, 100, 250, 600, 999, 1000, 4321, 7000, 30_000, 45_000, 90_000,
];

/// The 3DGS defaults, an odd hand-written schedule, and one with resets and the SH schedule off.
fn schedules() -> Vec<GeometryConfig> {
    let default = GeometryConfig::default();
    let mut odd = GeometryConfig {
        iterations: 1237,
        sh_degree_interval: 97,
        test_iterations: vec![1, 300, 301, 1237],
        save_iterations: vec![600, 1237],
        checkpoint_iterations: vec![5, 1236],
        ..GeometryConfig::default()
    };
    odd.learning_rates.position_lr_max_steps = 1237;
    odd.learning_rates.position_lr_delay_steps = 40;
    odd.densify = DensifyConfig {
        densification_interval: 37,
        densify_from_iter: 101,
        densify_until_iter: 900,
        opacity_reset_interval: 420,
        ..DensifyConfig::default()
    };
    let mut off = GeometryConfig {
        iterations: 5000,
        sh_degree_interval: 0,
        test_iterations: vec![2500, 5000],
        save_iterations: vec![5000],
        ..GeometryConfig::default()
    };
    off.densify.opacity_reset_interval = 0;
    off.densify.densify_until_iter = 2500;
    vec![default, odd, off]
}

/// The lists of event iterations of a schedule: test, save, checkpoint.
fn lists(c: &GeometryConfig) -> [&Vec<u64>; 3] {
    [
        &c.test_iterations,
        &c.save_iterations,
        &c.checkpoint_iterations,
    ]
}

/// The points in time of a schedule, in a fixed order: the position rate's decay length and
/// warm-up, the densification window, the first and last entry of each event list, the end.
/// (Scaling may merge neighbouring list entries, but never empties a list.)
fn points(c: &GeometryConfig) -> Vec<u64> {
    let mut p = vec![
        c.learning_rates.position_lr_max_steps,
        c.learning_rates.position_lr_delay_steps,
        c.densify.densify_from_iter,
        c.densify.densify_until_iter,
    ];
    for l in lists(c) {
        p.extend(l.iter().min());
        p.extend(l.iter().max());
    }
    p.push(c.iterations);
    p
}

/// The intervals of a schedule.
fn intervals(c: &GeometryConfig) -> [u64; 3] {
    [
        c.sh_degree_interval,
        c.densify.densification_interval,
        c.densify.opacity_reset_interval,
    ]
}

/// The shortest value a shortened run gives each of the [`intervals`].
const FLOORS: [u64; 3] = [1, MIN_DENSIFICATION_INTERVAL, MIN_OPACITY_RESET_INTERVAL];

/// The iterations at which something happens in a run of the schedule: density control,
/// opacity resets (white background), SH degree steps, test, save and checkpoint iterations.
fn events(c: &GeometryConfig) -> Vec<u64> {
    let mut e: Vec<u64> = (1..=c.iterations)
        .filter(|&i| {
            c.densify.densifies_at(i)
                || c.densify.resets_opacity_at(i, true)
                || (c.sh_degree_interval > 0 && i % c.sh_degree_interval == 0)
        })
        .collect();
    for l in lists(c) {
        e.extend(l.iter().filter(|&&t| t <= c.iterations));
    }
    e
}

#[test]
fn scaling_to_the_configured_length_changes_nothing() {
    for c in schedules() {
        assert_eq!(c.scaled_to(c.iterations), c);
    }
}

#[test]
fn every_event_of_the_run_stays_within_the_scaled_run() {
    for c in schedules() {
        for n in LENGTHS {
            let s = c.scaled_to(n);
            assert_eq!(s.iterations, n);
            // Points of the original run map into the scaled one, those beyond it stay beyond.
            for (before, after) in points(&c).into_iter().zip(points(&s)) {
                if (1..=c.iterations).contains(&before) {
                    assert!((1..=n).contains(&after), "n={n}: {before} -> {after}");
                } else if before > c.iterations {
                    assert!(after > n, "n={n}: {before} -> {after}");
                }
            }
            if c.learning_rates.position_lr_max_steps == c.iterations {
                assert_eq!(s.learning_rates.position_lr_max_steps, n);
            }
            assert!(events(&s).iter().all(|&e| (1..=n).contains(&e)));
            // The last density-control pass leaves the run time to refine: never at its end.
            assert!(!s.densify.densifies_at(n), "n={n}");
        }
    }
}

#[test]
fn events_keep_their_order() {
    for c in schedules() {
        let before = points(&c);
        for n in LENGTHS {
            let s = c.scaled_to(n);
            for (l0, l1) in lists(&c).into_iter().zip(lists(&s)) {
                assert_eq!(l0.is_empty(), l1.is_empty(), "n={n}");
                assert!(l1.len() <= l0.len(), "n={n}");
                if l0.is_sorted() {
                    assert!(l1.is_sorted(), "n={n}: {l0:?} -> {l1:?}");
                }
            }
            let after = points(&s);
            assert_eq!(after.len(), before.len());
            for i in 0..before.len() {
                for j in 0..before.len() {
                    if before[i] <= before[j] {
                        assert!(after[i] <= after[j], "n={n}: {before:?} -> {after:?}");
                    }
                }
            }
        }
    }
}

#[test]
fn intervals_stay_at_least_one_step_and_off_stays_off() {
    for c in schedules() {
        for n in LENGTHS {
            let s = c.scaled_to(n);
            for (before, after) in intervals(&c).into_iter().zip(intervals(&s)) {
                assert_eq!(before == 0, after == 0, "n={n}");
                assert!(before == 0 || after >= 1, "n={n}");
            }
        }
    }
}

#[test]
fn shortened_density_intervals_keep_their_floors() {
    for c in schedules() {
        let d = c.densify;
        for n in LENGTHS.into_iter().filter(|&n| n < c.iterations) {
            let s = c.scaled_to(n).densify;
            assert!(
                s.densification_interval
                    >= d.densification_interval.min(MIN_DENSIFICATION_INTERVAL)
            );
            if d.opacity_reset_interval > 0 {
                assert!(
                    s.opacity_reset_interval
                        >= d.opacity_reset_interval.min(MIN_OPACITY_RESET_INTERVAL)
                );
            }
            // Never longer than the configured intervals: a shorter run is never sparser.
            assert!(s.densification_interval <= d.densification_interval);
            assert!(s.opacity_reset_interval <= d.opacity_reset_interval);
        }
    }
}

#[test]
fn stretched_intervals_and_window_scale_in_proportion() {
    for c in schedules() {
        let n = 3 * c.iterations;
        let s = c.scaled_to(n);
        for (before, after) in intervals(&c).into_iter().zip(intervals(&s)) {
            assert_eq!(after, 3 * before);
        }
        assert_eq!(s.densify.densify_from_iter, 3 * c.densify.densify_from_iter);
        assert_eq!(
            s.densify.densify_until_iter,
            3 * c.densify.densify_until_iter
        );
    }
}

#[test]
fn scaling_there_and_back_restores_the_schedule_within_rounding() {
    for c in schedules() {
        let big = c.iterations;
        for n in LENGTHS {
            let back = c.scaled_to(n).scaled_to(big);
            assert_eq!(back.iterations, big);
            // Each rounding is at most half a step of its length; back at the configured
            // length, the first one is worth `big / n` steps.
            let tolerance = big.div_ceil(n);
            let (p0, p1) = (points(&c), points(&back));
            for (a, b) in p0.iter().zip(&p1).filter(|(&a, _)| a <= big) {
                assert!(a.abs_diff(*b) <= tolerance, "n={n}: {p0:?} -> {p1:?}");
            }
            // Every event comes back near one of the original events, and every original
            // event has one near it.
            let near = |x: u64, l: &[u64]| l.iter().any(|&y| x.abs_diff(y) <= tolerance);
            for (l0, l1) in lists(&c).into_iter().zip(lists(&back)) {
                assert!(l1.iter().all(|&x| near(x, l0)), "n={n}: {l0:?} -> {l1:?}");
                assert!(l0.iter().all(|&x| near(x, l1)), "n={n}: {l0:?} -> {l1:?}");
            }
            // Stretching and shortening back loses nothing to the floors when the interval is
            // not below its floor, so the intervals come back too.
            if n >= big {
                let restored = intervals(&c).into_iter().zip(intervals(&back));
                for ((a, b), floor) in restored.zip(FLOORS).filter(|((a, _), f)| a >= f) {
                    assert!(a.abs_diff(b) <= 1, "n={n}: {a} -> {b} (floor {floor})");
                }
            }
        }
    }
}

#[test]
fn the_position_rate_decays_over_the_scaled_run() {
    let c = GeometryConfig::default();
    let full = c.learning_rates.position_schedule(1.0);
    for n in [600, 1000, 90_000] {
        let s = c.scaled_to(n).learning_rates.position_schedule(1.0);
        // The same rates at the same fractions of the run.
        for k in 0..=4 {
            let (a, b) = (full.at(k * c.iterations / 4), s.at(k * n / 4));
            assert!((a - b).abs() <= 1e-12 * a, "n={n}, {k}/4: {a} vs {b}");
        }
    }
}
