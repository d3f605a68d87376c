//! TOML configuration files of the training commands.
//!
//! Every training command reads an optional `--config FILE.toml` holding its configuration
//! struct (any `serde` type with defaults: missing keys keep their default), applies its
//! command-line flags on top, and saves the effective configuration as `config.toml` beside its
//! outputs, so a run can be repeated with `--config OUT/config.toml`.
//!
//! A key the configuration does not know (a typo, a key of another command) is an error naming
//! the file and the key, rather than being silently ignored: the file is read as a TOML table,
//! deserialised, serialised back, and every key of the input missing from the round trip is
//! reported. Keys of earlier versions that no longer mean anything ([`RETIRED_KEYS`]) are
//! accepted and dropped, so that the `config.toml` of an older run still resumes.

use std::path::{Path, PathBuf};

use crate::error::{bail, Context, Result};
use serde::de::DeserializeOwned;
use serde::Serialize;

/// The name of the effective configuration written beside a command's outputs.
pub const CONFIG_FILE: &str = "config.toml";

/// Keys, at any level, that earlier versions wrote and that are now ignored: `progress` (whether
/// to draw progress bars is the front end's choice, e.g. `--no-progress`).
pub const RETIRED_KEYS: &[&str] = &["progress"];

/// Removes the [`RETIRED_KEYS`] from `table` and its sub-tables.
fn drop_retired(table: &mut toml::Table) {
    table.retain(|k, _| !RETIRED_KEYS.contains(&k));
    for (_, v) in table.iter_mut() {
        if let toml::Value::Table(t) = v {
            drop_retired(t);
        }
    }
}

/// Parses a configuration from TOML text; `origin` names the source in errors.
pub fn parse<T: DeserializeOwned + Serialize>(text: &str, origin: &Path) -> Result<T> {
    let mut table: toml::Table =
        toml::from_str(text).with_context(|| format!("{}: not a TOML file", origin.display()))?;
    drop_retired(&mut table);
    let config: T = T::deserialize(toml::Value::Table(table.clone()))
        .with_context(|| format!("{}: not a valid configuration", origin.display()))?;
    let round_trip = toml::Value::try_from(&config)
        .with_context(|| format!("{}: configuration cannot be serialised", origin.display()))?;
    let mut unknown = Vec::new();
    unknown_keys(&toml::Value::Table(table), &round_trip, "", &mut unknown);
    if !unknown.is_empty() {
        bail!(
            "{}: unknown configuration key{} {}",
            origin.display(),
            if unknown.len() > 1 { "s" } else { "" },
            unknown.join(", ")
        );
    }
    Ok(config)
}

/// Collects the dotted paths of keys of `given` that `known` lacks.
fn unknown_keys(given: &toml::Value, known: &toml::Value, prefix: &str, out: &mut Vec<String>) {
    if let (toml::Value::Table(g), toml::Value::Table(k)) = (given, known) {
        for (key, value) in g {
            let path = if prefix.is_empty() {
                key.clone()
            } else {
                format!("{prefix}.{key}")
            };
            match k.get(key) {
                None => out.push(format!("`{path}`")),
                Some(kv) => unknown_keys(value, kv, &path, out),
            }
        }
    }
}

/// The effective configuration of a training command writing into `out_dir`: the file `config`
/// when given, otherwise, when resuming, the run's saved `config.toml` if there is one,
/// otherwise the defaults; `overrides` (the command-line flags) are applied on top.
pub fn effective<T: DeserializeOwned + Serialize + Default>(
    config: Option<&Path>,
    resuming: bool,
    out_dir: &Path,
    overrides: impl FnOnce(&mut T),
) -> Result<T> {
    let saved = out_dir.join(CONFIG_FILE);
    let base = match config {
        Some(p) => Some(p.to_path_buf()),
        None if resuming && saved.is_file() => Some(saved),
        None => None,
    };
    let mut c: T = load(base.as_deref())?;
    overrides(&mut c);
    Ok(c)
}

/// Reads the configuration in `path`, or the default without a path.
pub fn load<T: DeserializeOwned + Serialize + Default>(path: Option<&Path>) -> Result<T> {
    match path {
        None => Ok(T::default()),
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("reading configuration {}", p.display()))?;
            parse(&text, p)
        }
    }
}

/// The configuration as TOML text.
pub fn to_toml<T: Serialize>(config: &T) -> Result<String> {
    toml::to_string(config).context("serialising the configuration")
}

/// Writes the effective configuration to `dir/config.toml` (atomically) and returns its path.
pub fn save<T: Serialize>(config: &T, dir: &Path) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let path = dir.join(CONFIG_FILE);
    base::write_atomic(&path, to_toml(config)?.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Default, PartialEq, Serialize, Deserialize)]
    #[serde(default)]
    struct Inner {
        rate: f64,
    }

    #[derive(Debug, Default, PartialEq, Serialize, Deserialize)]
    #[serde(default)]
    struct Demo {
        steps: u64,
        inner: Inner,
    }

    #[test]
    fn missing_keys_take_defaults_and_values_round_trip() {
        let c: Demo = parse("steps = 7", Path::new("a.toml")).unwrap();
        assert_eq!(
            c,
            Demo {
                steps: 7,
                inner: Inner { rate: 0.0 }
            }
        );
        let again: Demo = parse(&to_toml(&c).unwrap(), Path::new("b.toml")).unwrap();
        assert_eq!(again, c);
    }

    #[test]
    fn unknown_keys_are_named() {
        let e = parse::<Demo>("steps = 1\n[inner]\nrat = 2.0\n", Path::new("cfg.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cfg.toml") && e.contains("`inner.rat`"), "{e}");
        let e = parse::<Demo>("step = 1", Path::new("cfg.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("`step`"), "{e}");
    }

    #[test]
    fn wrong_types_are_refused() {
        let e = parse::<Demo>("steps = \"many\"", Path::new("cfg.toml")).unwrap_err();
        assert!(format!("{e:#}").contains("cfg.toml"));
    }

    #[test]
    fn retired_keys_of_older_runs_are_ignored_at_any_level() {
        let text = "steps = 3\nprogress = false\n[inner]\nrate = 0.5\nprogress = true\n";
        let c: Demo = parse(text, Path::new("old.toml")).unwrap();
        assert_eq!(
            c,
            Demo {
                steps: 3,
                inner: Inner { rate: 0.5 }
            }
        );
    }

    #[test]
    fn the_effective_configuration_prefers_the_file_then_the_saved_one_when_resuming() {
        let dir = std::env::temp_dir().join(format!("dsgs-config-{}", std::process::id()));
        let saved = Demo {
            steps: 9,
            inner: Inner { rate: 1.0 },
        };
        save(&saved, &dir).unwrap();
        let bump = |c: &mut Demo| c.steps += 1;
        let fresh: Demo = effective(None, false, &dir, bump).unwrap();
        assert_eq!(fresh.steps, 1);
        let resumed: Demo = effective(None, true, &dir, bump).unwrap();
        assert_eq!(resumed.steps, 10);
        let other = dir.join("other.toml");
        std::fs::write(&other, "steps = 2").unwrap();
        let given: Demo = effective(Some(&other), true, &dir, bump).unwrap();
        assert_eq!(given.steps, 3);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
