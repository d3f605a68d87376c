//! The command-line face of the settings: value parsers and help texts for the `clap`
//! arguments that the settings types declare.
//!
//! The settings that map onto flags derive [`clap::Args`], so that a program flattens them
//! into its commands (`#[command(flatten)]`) and gets the settings without copying them field
//! by field; used as plain structs, they are the settings they always were:
//! * the flags overriding a configuration file:
//!   [`GeometryOverrides`](crate::fit_geometry::GeometryOverrides),
//!   [`DecoderOverrides`](crate::pretrain_decoder::DecoderOverrides),
//!   [`FeatureOverrides`](crate::fit_features::FeatureOverrides),
//!   [`BakeOverrides`](crate::bake::BakeOverrides);
//! * whole commands' settings: [`FitSettings`](crate::fit_geometry::FitSettings),
//!   [`DemoSettings`](crate::demo::DemoSettings),
//!   [`StylizeImageSettings`](crate::stylize_image::StylizeImageSettings);
//! * groups: [`NetworkFiles`](crate::pretrain_decoder::NetworkFiles),
//!   [`CameraArgs`](crate::cameras::CameraArgs),
//!   [`WarpOptions`](crate::consistency::WarpOptions).
//!
//! A field that a program shows elsewhere in its help (a run flag listed with the others, an
//! output listed last) is `#[arg(skip)]`, and the struct's documentation says so: the program
//! declares that flag and fills the field.
//!
//! Conventions of the parsers here:
//! * out-of-range numbers are refused while the arguments are parsed; the message names the
//!   range and `clap` adds the flag (`invalid value '0' for '--iterations <ITERATIONS>': must be
//!   at least 1`);
//! * an enumerated value lists its allowed values in `--help` and in the error for any other;
//! * a flag overriding a configuration file has no `clap` default (absent, it leaves the file's
//!   value), so its help states the configuration's default, taken from the configuration's
//!   `Default` through [`with_default`] so that it cannot drift;
//! * an unexpected value in a command with a repeated path flag gets a tip on repeating flags
//!   ([`with_repeat_tip`]).

use std::fmt::Display;
use std::str::FromStr;

use clap::builder::{PossibleValue, PossibleValuesParser, StyledStr, TypedValueParser};
use clap::error::{ContextKind, ContextValue, ErrorKind};
use clap::ArgAction;
use glam::DVec3;
use train::{DecoderMode, FeatureNorm, Variant};

/// The help of `--config` of the commands that save their configuration as `OUT/config.toml`.
pub const CONFIG_HELP: &str = "TOML configuration (keys: docs/configuration.md); flags override \
                               it [default: none: the built-in defaults, or OUT/config.toml when \
                               resuming]";

/// The help of `bake --config` (a bake records its configuration in its JSON report).
pub const BAKE_CONFIG_HELP: &str = "TOML configuration (keys: docs/configuration.md); flags \
                                    override it [default: none: the built-in defaults]";

/// `text` followed by its default in `clap`'s `[default: VALUE]` form.
pub fn with_default(text: &str, default: impl Display) -> String {
    format!("{text} [default: {default}]")
}

/// A comma-separated list, or `none`.
pub fn list<T: Display>(values: &[T]) -> String {
    if values.is_empty() {
        return "none".into();
    }
    let v: Vec<String> = values.iter().map(T::to_string).collect();
    v.join(",")
}

/// A parser accepting exactly `names`, listed in `--help` and in the error for any other value.
pub fn one_of<T>(names: impl IntoIterator<Item = &'static str>) -> impl TypedValueParser<Value = T>
where
    T: FromStr<Err = String> + Clone + Send + Sync + 'static,
{
    PossibleValuesParser::new(names).try_map(|s| s.parse::<T>())
}

/// [`one_of`] that also accepts other spellings, `(alias, name)`, e.g. `color` for `colour`
/// (not listed in `--help`; `T::from_str` must accept them too).
pub fn one_of_or_alias<T>(
    names: &'static [&'static str],
    aliases: &'static [(&'static str, &'static str)],
) -> impl TypedValueParser<Value = T>
where
    T: FromStr<Err = String> + Clone + Send + Sync + 'static,
{
    let values = names.iter().map(|&name| {
        let of = aliases.iter().filter(move |(_, n)| *n == name);
        PossibleValue::new(name).aliases(of.map(|(a, _)| *a))
    });
    PossibleValuesParser::new(values).try_map(|s| s.parse::<T>())
}

/// The `--variant` parser: `standard` or `fullres`, listed in `--help`.
pub fn variant() -> impl TypedValueParser<Value = Variant> {
    // The match makes a new variant fail to compile here until it is listed.
    let listed = |v: Variant| match v {
        Variant::Standard | Variant::Fullres => v.as_str(),
    };
    one_of([listed(Variant::Standard), listed(Variant::Fullres)])
}

/// The `--decoder-mode` parser: `pretrained`, `scratch` or `mlp`, listed in `--help`.
pub fn decoder_mode() -> impl TypedValueParser<Value = DecoderMode> {
    let listed = |v: DecoderMode| match v {
        DecoderMode::Pretrained | DecoderMode::Scratch | DecoderMode::Mlp => v.as_str(),
    };
    one_of([
        listed(DecoderMode::Pretrained),
        listed(DecoderMode::Scratch),
        listed(DecoderMode::Mlp),
    ])
}

/// The `--normalize` parser: `before-raster` or `after-raster`, listed in `--help`.
pub fn feature_norm() -> impl TypedValueParser<Value = FeatureNorm> {
    let listed = |v: FeatureNorm| match v {
        FeatureNorm::BeforeRaster | FeatureNorm::AfterRaster => v.as_str(),
    };
    one_of([
        listed(FeatureNorm::BeforeRaster),
        listed(FeatureNorm::AfterRaster),
    ])
}

/// A whole number in `min..=max`; the message names the range.
pub fn whole_in<T>(min: T, max: T) -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync
where
    T: FromStr + PartialOrd + Display + Copy + Send + Sync + 'static,
{
    move |s: &str| {
        let v: T = s
            .trim()
            .parse()
            .map_err(|_| format!("`{s}` is not a whole number"))?;
        if v < min || v > max {
            return Err(format!("must be between {min} and {max}"));
        }
        Ok(v)
    }
}

/// A whole number of at least 1 (a count where 0 means nothing: iterations, frames, sizes).
pub fn at_least_one<T>() -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync
where
    T: FromStr + PartialOrd + Display + Copy + From<u8> + Send + Sync + 'static,
{
    |s: &str| {
        let v: T = s
            .trim()
            .parse()
            .map_err(|_| format!("`{s}` is not a whole number"))?;
        if v < T::from(1) {
            return Err("must be at least 1".into());
        }
        Ok(v)
    }
}

/// A finite number.
pub fn finite(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number"))?;
    if !v.is_finite() {
        return Err("must be a finite number".into());
    }
    Ok(v)
}

/// A finite number above 0 (a factor, a rate of frames, a tolerance).
pub fn positive(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v <= 0.0 {
        return Err("must be a finite number above 0".into());
    }
    Ok(v)
}

/// A finite number of 0 or more (a weight, a learning rate).
pub fn non_negative(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v < 0.0 {
        return Err("must be a finite number, 0 or more".into());
    }
    Ok(v)
}

/// A number in [0, 1] (a strength, an alpha level).
pub fn fraction(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if !(0.0..=1.0).contains(&v) {
        return Err("must be in [0, 1]".into());
    }
    Ok(v)
}

/// An `x,y,z` direction: three finite numbers, not all zero.
pub fn direction(s: &str) -> Result<DVec3, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f64>()
                .map_err(|_| format!("`{x}` is not a number"))
        })
        .collect::<Result<_, _>>()?;
    let d = match v.as_slice() {
        [x, y, z] => DVec3::new(*x, *y, *z),
        _ => return Err(format!("expected three comma-separated numbers, got `{s}`")),
    };
    if !d.is_finite() || d == DVec3::ZERO {
        return Err(format!("`{s}` is not a direction (finite and not zero)"));
    }
    Ok(d)
}

/// A background colour: `white`, `black`, or `r,g,b` with each channel in `[0, 1]`.
pub fn background(s: &str) -> Result<[f32; 3], String> {
    match s.trim() {
        "white" => return Ok([1.0; 3]),
        "black" => return Ok([0.0; 3]),
        _ => {}
    }
    let v: Vec<f32> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f32>()
                .map_err(|_| format!("`{x}` is not a number (or give white or black)"))
        })
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [r, g, b] if [r, g, b].iter().all(|c| (0.0..=1.0).contains(*c)) => Ok([*r, *g, *b]),
        [_, _, _] => Err(format!("`{s}`: each channel must be in [0, 1]")),
        _ => Err(format!(
            "expected white, black or three comma-separated numbers in [0, 1], got `{s}`"
        )),
    }
}

/// An amount of memory in MiB: 1 to 1048576 (1 TiB).
pub fn mebibytes() -> impl TypedValueParser<Value = u64> {
    clap::value_parser!(u64).range(1..=1 << 20)
}

/// `--weights` where it used to mean the weights of a style mixture (stylize, eval, bake):
/// always refused, pointing to `--mix`.
pub fn renamed_to_mix(_: &str) -> Result<String, String> {
    Err(
        "the weights of a style mixture are given with --mix (comma-separated, one per \
         --style); --weights names a network weights file, which this command does not take"
            .into(),
    )
}

/// The tip added to an unexpected positional argument: most likely a second value given to a
/// one-value path flag.
const REPEAT_TIP: &str = "a flag takes one path per occurrence: repeat it for several, as in \
                          '--style a.jpg --style b.jpg'";

/// Adds a tip on repeating flags to an unexpected-argument error about a value (not a flag) of a command
/// with a flag repeated for several values (`sub`).
pub fn with_repeat_tip(mut e: clap::Error, sub: Option<&clap::Command>) -> clap::Error {
    let about_a_value = matches!(
        e.get(ContextKind::InvalidArg),
        Some(ContextValue::String(a)) if !a.starts_with('-')
    );
    let repeats = sub.is_some_and(|c| {
        c.get_arguments()
            .any(|a| a.get_action().takes_values() && matches!(a.get_action(), ArgAction::Append))
    });
    if e.kind() == ErrorKind::UnknownArgument && about_a_value && repeats {
        let mut tips = match e.get(ContextKind::Suggested) {
            Some(ContextValue::StyledStrs(t)) => t.clone(),
            _ => Vec::new(),
        };
        tips.push(StyledStr::from(REPEAT_TIP));
        e.insert(ContextKind::Suggested, ContextValue::StyledStrs(tips));
    }
    e
}

/// The help of `--networks` (`run`, `demo`).
pub const NETWORKS_HELP: &str = "Networks: relu4_1 (the compressed VGG-19 encoder to relu4_1 \
    from SHARED/weights/compressed-16x-relu4_1 with dsgs's pre-trained decoder, built in; stage 3 \
    fits the features by the alignment loss alone and renders the feature map 8 times finer and \
    averages it) or wct-relu3_1 (the VGG-19 encoder to relu3_1 and the WCT reconstruction \
    decoder from SHARED/weights/wct-relu1_1-3_1; the paper's stage-3 losses, direct render)";

#[cfg(test)]
mod tests {
    use super::*;
    use train::bake::STORED_SH_DEGREE;

    #[test]
    fn range_parsers_accept_their_ends_and_refuse_what_lies_outside() {
        assert_eq!(fraction("0"), Ok(0.0));
        assert_eq!(fraction("1"), Ok(1.0));
        for bad in ["-0.01", "1.01", "NaN", "inf", "x"] {
            assert!(fraction(bad).is_err(), "{bad}");
        }
        assert!(positive("1e-9").is_ok());
        for bad in ["0", "-1", "inf", "-inf"] {
            assert!(positive(bad).is_err(), "{bad}");
        }
        assert_eq!(non_negative("0"), Ok(0.0));
        assert!(non_negative("-1e-9").is_err());
        let degree = whole_in(0usize, STORED_SH_DEGREE);
        assert_eq!(degree("0"), Ok(0));
        assert_eq!(degree("3"), Ok(3));
        assert!(degree("4").is_err() && degree("-1").is_err() && degree("1.5").is_err());
        let count = at_least_one::<u64>();
        assert_eq!(count("1"), Ok(1));
        assert!(count("0").is_err());
        assert_eq!(direction("0, 1,-0.5"), Ok(DVec3::new(0.0, 1.0, -0.5)));
        for bad in ["0,0,0", "1,2", "1,nan,0", "1,inf,0"] {
            assert!(direction(bad).is_err(), "{bad}");
        }
        assert_eq!(background("white"), Ok([1.0; 3]));
        assert_eq!(background("black"), Ok([0.0; 3]));
        assert_eq!(background("0, 0.5,1"), Ok([0.0, 0.5, 1.0]));
        for bad in ["grey", "1,1", "0,0,1.5", "-0.1,0,0", "nan,0,0"] {
            assert!(background(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn defaults_are_added_in_the_form_clap_shows_them() {
        assert_eq!(with_default("Seed", 0), "Seed [default: 0]");
        assert_eq!(list::<u64>(&[]), "none");
        assert_eq!(list(&[7000, 30000]), "7000,30000");
    }
}
