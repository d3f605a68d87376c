//! The command line's conventions, checked at argument parsing (no data needed): path-list flags
//! take one value per occurrence and are repeated; `--weights` is a network weights file and
//! `--mix` the weights of a style mixture; `--help` shows every flag's default (from the
//! configurations' `Default`) and allowed values; every long-running command takes
//! `--no-progress`; out-of-range numbers are refused while parsing, naming the flag and the
//! range. Also: every key of every `--config` file is documented in `docs/configuration.md`.

mod common;

use std::path::Path;
use std::process::Output;

use common::{dsgs, scratch};
use pipeline::fit_features::FitFeaturesConfig;
use pipeline::fit_geometry::FitGeometryConfig;
use train::{BakeConfig, DecoderTrainConfig};

/// Exit status of an argument-parsing error (clap's convention).
const USAGE_EXIT: i32 = 2;

fn run(args: &[&str]) -> Output {
    dsgs().args(args).output().expect("the dsgs binary runs")
}

/// The `--help` text of a subcommand.
fn help(command: &str) -> String {
    let out = run(&[command, "--help"]);
    assert!(out.status.success(), "{command} --help failed");
    String::from_utf8(out.stdout).unwrap()
}

/// The help paragraph of `flag` in `help`: its line and the following ones up to the next flag.
fn flag_help(help: &str, flag: &str) -> String {
    let lines: Vec<&str> = help.lines().collect();
    let start = lines
        .iter()
        .position(|l| {
            let t = l.trim_start();
            t.starts_with(&format!("{flag} "))
                || t == flag
                || t.contains(&format!(", {flag} "))
                || t.ends_with(&format!(", {flag}"))
        })
        .unwrap_or_else(|| panic!("{flag} is not in\n{help}"));
    let mut text = lines[start].to_string();
    for l in &lines[start + 1..] {
        if l.trim_start().starts_with('-') || l.trim().is_empty() {
            break;
        }
        text.push(' ');
        text.push_str(l.trim());
    }
    text
}

/// Runs `args`, which must fail at argument parsing; returns the error output.
fn parse_error(args: &[&str]) -> String {
    let out = run(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(USAGE_EXIT), "{args:?}: {err}");
    assert!(err.starts_with("error: "), "{err}");
    err
}

/// Runs `args`, which must get past argument parsing (and then fail on the missing inputs
/// every test here gives, with the program's own error).
fn parses(args: &[&str]) {
    let out = run(args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
    assert!(err.starts_with("error: "), "{args:?}: {err}");
    assert!(!err.contains("Usage:"), "{args:?} failed to parse: {err}");
}

fn s(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 scratch path")
}

#[test]
fn path_list_flags_take_one_value_per_occurrence_and_are_repeated() {
    let dir = scratch("flags-repeat");
    let missing = dir.join("missing");
    let m = s(&missing);
    let out = dir.join("out");
    let o = s(&out);
    let ply = dir.join("out.ply");
    // Repeating the flag parses in every command (then the missing inputs are reported).
    parses(&[
        "stylize", m, "--style", "a.jpg", "--style", "b.jpg", "-o", o,
    ]);
    parses(&["eval", m, "--style", "a.jpg", "--style", "b.jpg"]);
    let bake = [
        "bake", m, "--style", "a.jpg", "--style", "b.jpg", "--mix", "1,1", "-o",
    ];
    parses(&[&bake[..], &[s(&ply)]].concat());
    parses(&[
        "pretrain-decoder",
        "--content",
        m,
        "--content",
        m,
        "--style",
        m,
        "--style",
        m,
        "-o",
        o,
    ]);
    parses(&[
        "fit-features",
        m,
        "--geometry",
        m,
        "--style",
        "a.jpg",
        "--style",
        "b.jpg",
        "--weights",
        m,
        "-o",
        o,
    ]);
    parses(&[
        "demo", "--shared", m, "-o", o, "--style", "a.jpg", "--style", "b.jpg",
    ]);
    // Several values after one flag are refused, with a tip naming the convention.
    let tip = "--style a.jpg --style b.jpg";
    for args in [
        &["stylize", "--style", "a.jpg", "b.jpg", "BUNDLE", "-o", o][..],
        &["eval", "--style", "a.jpg", "b.jpg", "BUNDLE"],
        &["bake", "--style", "a.jpg", "b.jpg", "BUNDLE", "-o", "x.ply"],
        &["demo", "--shared", m, "--style", "a.jpg", "b.jpg"],
        &[
            "pretrain-decoder",
            "--content",
            "a",
            "b",
            "--style",
            "c",
            "-o",
            o,
        ],
    ] {
        let err = parse_error(args);
        assert!(err.contains("unexpected argument"), "{err}");
        assert!(err.contains(tip), "{args:?}: {err}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn weights_names_network_files_and_mix_the_weights_of_a_style_mixture() {
    for command in ["stylize", "eval", "bake"] {
        let h = help(command);
        assert!(
            flag_help(&h, "--mix").contains("one per style image"),
            "{h}"
        );
        assert!(!h.contains("--weights"), "{command}: {h}");
    }
    for command in ["fit-features", "pretrain-decoder", "demo"] {
        let h = help(command);
        assert!(
            flag_help(&h, "--weights").contains("network weights"),
            "{h}"
        );
        assert!(!h.contains("--mix"), "{command}: {h}");
    }
    // The old spelling of the mixture is refused, pointing to --mix.
    for args in [
        &[
            "stylize",
            "B",
            "--style",
            "a.jpg",
            "--weights",
            "1",
            "-o",
            "o",
        ][..],
        &["eval", "B", "--style", "a.jpg", "--weights", "1"],
        &[
            "bake",
            "B",
            "--style",
            "a.jpg",
            "--weights",
            "1",
            "-o",
            "x.ply",
        ],
    ] {
        let err = parse_error(args);
        assert!(err.contains("--weights") && err.contains("--mix"), "{err}");
    }
}

#[test]
fn help_shows_the_configuration_defaults_of_the_training_flags() {
    let g = FitGeometryConfig::default();
    let d = DecoderTrainConfig::default();
    let f = FitFeaturesConfig::default();
    let b = BakeConfig::default();
    let list = |v: &[u64]| {
        let s: Vec<String> = v.iter().map(u64::to_string).collect();
        s.join(",")
    };
    let expected: Vec<(&str, &str, String)> = vec![
        (
            "fit-geometry",
            "--iterations",
            g.geometry.iterations.to_string(),
        ),
        (
            "fit-geometry",
            "--downscale",
            g.dataset.downscale.to_string(),
        ),
        (
            "fit-geometry",
            "--test-iterations",
            list(&g.geometry.test_iterations),
        ),
        ("fit-geometry", "--seed", g.geometry.seed.to_string()),
        (
            "fit-geometry",
            "--sh-degree",
            g.geometry.sh_degree.to_string(),
        ),
        (
            "fit-geometry",
            "--checkpoint-every",
            g.geometry.checkpoint_interval.to_string(),
        ),
        (
            "fit-geometry",
            "--log-every",
            g.geometry.log_interval.to_string(),
        ),
        ("pretrain-decoder", "--iterations", d.iterations.to_string()),
        ("pretrain-decoder", "--batch-size", d.batch_size.to_string()),
        ("pretrain-decoder", "--crop", d.crop.to_string()),
        ("pretrain-decoder", "--resize", d.resize.to_string()),
        (
            "pretrain-decoder",
            "--style-weight",
            d.style_weight.to_string(),
        ),
        ("pretrain-decoder", "--lr", d.lr.to_string()),
        (
            "pretrain-decoder",
            "--variant",
            d.variant.as_str().to_string(),
        ),
        (
            "pretrain-decoder",
            "--checkpoint-every",
            d.checkpoint_interval.to_string(),
        ),
        (
            "fit-features",
            "--iterations",
            f.features.iterations.to_string(),
        ),
        (
            "fit-features",
            "--feature-dim",
            f.features.feature_dim.to_string(),
        ),
        (
            "fit-features",
            "--align-warmup",
            f.features.align_warmup.to_string(),
        ),
        (
            "fit-features",
            "--variant",
            f.features.variant.as_str().to_string(),
        ),
        (
            "fit-features",
            "--downscale",
            f.dataset.downscale.to_string(),
        ),
        (
            "fit-features",
            "--checkpoint-every",
            f.features.checkpoint_interval.to_string(),
        ),
        ("bake", "--iterations", b.iterations.to_string()),
        ("bake", "--sh-degree", b.sh_degree.to_string()),
        ("bake", "--lr", b.feature_lr.to_string()),
        ("bake", "--held-out", b.held_out.to_string()),
        ("bake", "--resolution-scale", b.resolution_scale.to_string()),
        (
            "bake",
            "--checkpoint-every",
            b.checkpoint_interval.to_string(),
        ),
    ];
    for (command, flag, default) in expected {
        let h = help(command);
        let text = flag_help(&h, flag);
        assert!(
            text.contains(&format!("[default: {default}")),
            "{command} {flag}: expected the default {default} in `{text}`"
        );
    }
}

#[test]
fn every_value_flag_shows_its_default_and_enumerated_flags_their_values() {
    let commands = [
        "fit-geometry",
        "pretrain-decoder",
        "fit-features",
        "bake",
        "render",
        "stylize",
        "eval",
        "demo",
        "run",
    ];
    for command in commands {
        let h = help(command);
        for line in h.lines() {
            let t = line.trim_start();
            // An option taking a value: `--name <VALUE>` (or `-o, --output <OUTPUT>`).
            let Some(flag) = t
                .split_whitespace()
                .find(|w| w.starts_with("--"))
                .filter(|_| t.starts_with('-') && t.contains(" <"))
            else {
                continue;
            };
            let flag = flag.trim_end_matches(',');
            let text = flag_help(&h, flag);
            let usage = h.lines().find(|l| l.starts_with("Usage:")).unwrap();
            let required = usage.contains(&format!("{flag} <"));
            let repeated = text.contains("repeat");
            assert!(
                required || repeated || text.contains("[default: "),
                "{command} {flag} shows no default: `{text}`"
            );
        }
        if h.contains("--variant") {
            let text = flag_help(&h, "--variant");
            assert!(
                text.contains("[possible values: standard, fullres]")
                    && text.contains("[default: "),
                "{command}: `{text}`"
            );
        }
    }
    let render = help("render");
    assert!(flag_help(&render, "--what").contains("[possible values: "));
    assert!(flag_help(&render, "--cameras").contains("[possible values: "));
    // Each command shows its own default camera source, and only that one.
    for (command, source) in [("render", "orbit"), ("stylize", "orbit"), ("eval", "dense")] {
        let text = flag_help(&help(command), "--cameras");
        assert_eq!(text.matches("[default: ").count(), 1, "{command}: `{text}`");
        assert!(
            text.contains(&format!("[default: {source}]")),
            "{command}: `{text}`"
        );
    }
}

#[test]
fn a_missing_required_input_is_a_usage_error_whichever_it_is() {
    // Without --style or without -o, stylize stops at parsing with the same status.
    let no_style = parse_error(&["stylize", "BUNDLE", "-o", "out"]);
    assert!(no_style.contains("--style"), "{no_style}");
    let no_output = parse_error(&["stylize", "BUNDLE", "--style", "a.jpg"]);
    assert!(no_output.contains("--output"), "{no_output}");
    parse_error(&["render", "-o", "out"]);
}

#[test]
fn every_long_running_command_takes_no_progress() {
    let commands = [
        "fit-geometry",
        "pretrain-decoder",
        "fit-features",
        "bake",
        "render",
        "stylize",
        "eval",
        "demo",
        "run",
    ];
    for command in commands {
        assert!(help(command).contains("--no-progress"), "{command}");
    }
    let dir = scratch("flags-no-progress");
    let missing = dir.join("missing.ply");
    parses(&[
        "render",
        "--scene",
        s(&missing),
        "-o",
        s(&dir.join("frames")),
        "--no-progress",
    ]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn out_of_range_numbers_are_refused_while_parsing_naming_flag_and_range() {
    let stylize = ["stylize", "B", "--style", "a.jpg", "-o", "o"];
    let render = ["render", "s.ply", "-o", "o"];
    let bake = ["bake", "B", "--style", "a.jpg", "-o", "x.ply"];
    let geometry = ["fit-geometry", "D", "-o", "o"];
    let decoder = [
        "pretrain-decoder",
        "--content",
        "c",
        "--style",
        "s",
        "-o",
        "o",
    ];
    let features = [
        "fit-features",
        "--geometry",
        "g.ply",
        "--dataset",
        "d",
        "--style",
        "s",
        "--weights",
        "w",
        "-o",
        "o",
    ];
    let eval = ["eval", "B", "--style", "a.jpg"];
    let cases: Vec<(&[&str], &[&str], &str)> = vec![
        (&stylize, &["--alpha", "5"], "[0, 1]"),
        (&stylize, &["--alpha=-0.5"], "[0, 1]"),
        (&stylize, &["--alpha", "NaN"], "finite"),
        (&bake, &["--alpha", "1.01"], "[0, 1]"),
        (&eval, &["--alpha", "2"], "[0, 1]"),
        (&stylize, &["--mix", "1,-2"], "0 or more"),
        (&stylize, &["--fps", "0"], "above 0"),
        (&stylize, &["--sheet-views", "0"], "at least 1"),
        (&stylize, &["--style-size", "0"], "at least 1"),
        (&render, &["--frames", "0"], "at least 1"),
        (&render, &["--scale", "0"], "above 0"),
        (&render, &["--scale", "inf"], "finite"),
        (&render, &["--width", "0"], "between 1 and"),
        (&render, &["--height", "100000"], "between 1 and"),
        (&render, &["--up", "0,0,0"], "not zero"),
        (&eval, &["--alpha-threshold", "1.5"], "[0, 1]"),
        (&eval, &["--depth-tolerance", "0"], "above 0"),
        (&geometry, &["--iterations", "0"], "at least 1"),
        (&geometry, &["--downscale", "0"], "above 0"),
        (&geometry, &["--resolution", "0"], "at least 1"),
        (&geometry, &["--sh-degree", "4"], "between 0 and 3"),
        (&decoder, &["--iterations", "0"], "at least 1"),
        (&decoder, &["--batch-size", "0"], "at least 1"),
        (&decoder, &["--crop", "0"], "at least 1"),
        (&decoder, &["--lr=-1"], "0 or more"),
        (&features, &["--feature-dim", "0"], "at least 1"),
        (&features, &["--downscale=-2"], "above 0"),
        (&bake, &["--sh-degree", "9"], "between 0 and 3"),
        (&bake, &["--resolution-scale", "0"], "above 0"),
        (&["demo"], &["--frames", "0"], "at least 1"),
        (&["demo"], &["--downscale", "0"], "above 0"),
    ];
    for (command, bad, range) in cases {
        let args = [command, bad].concat();
        let err = parse_error(&args);
        let flag = bad[0].split('=').next().unwrap();
        assert!(
            err.contains(&format!("'{flag} <")) && err.contains(range),
            "{args:?}: {err}"
        );
    }
    // The ends of a closed range are accepted.
    let dir = scratch("flags-range");
    let missing = dir.join("missing");
    for alpha in ["0", "1"] {
        parses(&[
            "stylize",
            s(&missing),
            "--style",
            "a.jpg",
            "--alpha",
            alpha,
            "-o",
            s(&dir.join("o")),
        ]);
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The dotted paths and values of every key of a TOML table, nested tables' keys included.
fn keys(table: &toml::Table, prefix: &str, out: &mut Vec<(String, toml::Value)>) {
    for (k, v) in table {
        let path = format!("{prefix}{k}");
        match v {
            toml::Value::Table(t) => keys(t, &format!("{path}."), out),
            _ => out.push((path, v.clone())),
        }
    }
}

/// The keys of a configuration and their values, serialised as a `config.toml` is.
fn config_keys<T: serde::Serialize>(config: &T) -> Vec<(String, toml::Value)> {
    let text = pipeline::config::to_toml(config).unwrap();
    let table: toml::Table = toml::from_str(&text).unwrap();
    let mut out = Vec::new();
    keys(&table, "", &mut out);
    out
}

/// The default column of a key's row in a section of docs/configuration.md, parsed as TOML
/// (the first `code` span); `None` when the default is written in words (an absent key).
fn documented_default(row: &str) -> Option<toml::Value> {
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    // | key | meaning | unit | default | allowed | flag |
    let default = cells.get(4)?;
    let code = default.strip_prefix('`')?.split('`').next()?;
    let t: toml::Table = toml::from_str(&format!("v = {code}")).ok()?;
    t.get("v").cloned()
}

#[test]
fn every_configuration_key_is_documented_with_its_default() {
    let doc = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/configuration.md"),
    )
    .unwrap();
    // Optional keys are absent from a serialised default; give them values so they appear.
    let mut geometry = FitGeometryConfig::default();
    geometry.dataset.images_folder = Some(2);
    let mut features = FitFeaturesConfig::default();
    features.dataset.images_folder = Some(2);
    features.features.crop = Some(32);
    let configs = [
        (
            "fit-geometry",
            config_keys(&geometry),
            config_keys(&FitGeometryConfig::default()),
        ),
        (
            "pretrain-decoder",
            config_keys(&DecoderTrainConfig::default()),
            config_keys(&DecoderTrainConfig::default()),
        ),
        (
            "fit-features",
            config_keys(&features),
            config_keys(&FitFeaturesConfig::default()),
        ),
        (
            "bake",
            config_keys(&BakeConfig::default()),
            config_keys(&BakeConfig::default()),
        ),
    ];
    for (command, all, defaults) in configs {
        // The command's section: from its heading to the next one.
        let heading = format!("## `dsgs {command}`");
        let start = doc
            .find(&heading)
            .unwrap_or_else(|| panic!("docs/configuration.md has no {heading} section"));
        let rest = &doc[start + heading.len()..];
        let section = &rest[..rest.find("\n## ").unwrap_or(rest.len())];
        assert!(all.len() > 5, "{command}: {all:?}");
        for (key, _) in all {
            let row = section
                .lines()
                .find(|l| l.starts_with(&format!("| `{key}` |")))
                .unwrap_or_else(|| {
                    panic!("docs/configuration.md does not document `{key}` of dsgs {command}")
                });
            // A key present in the serialised default documents that value.
            if let Some((_, value)) = defaults.iter().find(|(k, _)| *k == key) {
                assert_eq!(
                    documented_default(row).as_ref(),
                    Some(value),
                    "the documented default of `{key}` (dsgs {command}) is not the default"
                );
            }
        }
    }
}
