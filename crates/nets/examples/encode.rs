//! Runs the encoder on an image: prints each `relu{k}_1` feature's shape, mean and standard
//! deviation, and, when a decoder is given too, decodes the deepest level it accepts back to a
//! PNG and prints the reconstruction's PSNR.
//!
//! ```text
//! cargo run --release -p dsgs-nets --example encode -- WEIGHTS [WEIGHTS] IMAGE [options]
//! ```
//!
//! `WEIGHTS` is a canonical `.safetensors` file (as `dsgs weights import` writes it, encoder
//! and/or decoder) or a PyTorch `.pth` checkpoint holding an encoder or a decoder (imported with
//! `nets::checkpoint`; which of the two it is comes from its layers). Give an encoder checkpoint
//! and a decoder checkpoint to decode, e.g. `vgg_normalised_conv3_1.pth
//! feature_invertor_conv3_1.pth photo.jpg`.

use std::error::Error;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use image::imageops::FilterType;
use ndarray::{Array4, ArrayView4, Axis};
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, NetWeights, Resolution};

const USAGE: &str = "\
usage: encode WEIGHTS [WEIGHTS] IMAGE [options]
runs the encoder on IMAGE and prints each level's shape and statistics; with a decoder, decodes
the features back to a PNG

WEIGHTS: a canonical .safetensors file, or a PyTorch .pth encoder or decoder checkpoint

options:
  --out PATH       where to write the decoded image (default decoded.png)
  --max-side N     shrink the image so its longer side is at most N pixels (default 512, 0 = keep)
  --fullres        run the fullres variant (no pooling, no upsampling)";

struct Args {
    weights: Vec<PathBuf>,
    image: PathBuf,
    out: PathBuf,
    max_side: u32,
    resolution: Resolution,
}

fn main() -> ExitCode {
    let raw: Vec<String> = std::env::args().skip(1).collect();
    if raw.iter().any(|a| a == "-h" || a == "--help") {
        println!("{USAGE}");
        return ExitCode::SUCCESS;
    }
    // Bad arguments exit with 2 and the usage, failures with 1.
    let outcome = parse_args(&raw)
        .map_err(|e| (format!("{e}\n\n{USAGE}"), 2))
        .and_then(|a| run(&a).map_err(|e| (e.to_string(), 1)));
    if let Err((message, code)) = outcome {
        eprintln!("error: {message}");
        return ExitCode::from(code);
    }
    ExitCode::SUCCESS
}

fn parse_args(raw: &[String]) -> Result<Args, String> {
    let mut positional = Vec::new();
    let mut out = PathBuf::from("decoded.png");
    let mut max_side = 512;
    let mut resolution = Resolution::Standard;
    let mut it = raw.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--fullres" => resolution = Resolution::Fullres,
            "--out" | "--max-side" => {
                let v = it
                    .next()
                    .ok_or_else(|| format!("option {a} needs a value"))?;
                if a == "--out" {
                    out = v.into();
                } else {
                    max_side = v
                        .parse()
                        .map_err(|_| format!("invalid value `{v}` for {a}"))?;
                }
            }
            _ if a.starts_with("--") => return Err(format!("unknown option {a}")),
            _ => positional.push(PathBuf::from(a)),
        }
    }
    if !(2..=3).contains(&positional.len()) {
        return Err(format!(
            "expected one or two weights files and an image, got {} argument(s)",
            positional.len()
        ));
    }
    let image = positional.pop().expect("two or three");
    Ok(Args {
        weights: positional,
        image,
        out,
        max_side,
        resolution,
    })
}

/// Reads a canonical weights file, or a PyTorch checkpoint as an encoder or else a decoder.
fn load_weights(path: &Path) -> Result<NetWeights, Box<dyn Error>> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("safetensors"))
    {
        return Ok(NetWeights::load(path)?);
    }
    let sd = load_checkpoint(path)?;
    let mut w = NetWeights::default();
    match Encoder::from_state_dict(&sd) {
        Ok(e) => w.encoder = Some(e),
        Err(enc_err) => match Decoder::from_state_dict(&sd) {
            Ok(d) => w.decoder = Some(d),
            Err(dec_err) => {
                return Err(format!(
                    "{} holds neither an encoder nor a decoder\n  as an encoder: {enc_err}\n  \
                     as a decoder: {dec_err}",
                    path.display()
                )
                .into())
            }
        },
    }
    Ok(w)
}

/// The image as a `1 x 3 x H x W` array of RGB values in `[0, 1]`, shrunk (aspect kept) so its
/// longer side is at most `max_side` (0: any size).
fn load_image(path: &Path, max_side: u32) -> Result<Array4<f32>, Box<dyn Error>> {
    let mut img = image::open(path)
        .map_err(|e| format!("{}: {e}", path.display()))?
        .to_rgb32f();
    let side = img.width().max(img.height());
    if max_side > 0 && side > max_side {
        let s = max_side as f64 / side as f64;
        let w = ((img.width() as f64 * s).round() as u32).max(1);
        let h = ((img.height() as f64 * s).round() as u32).max(1);
        img = image::imageops::resize(&img, w, h, FilterType::Triangle);
    }
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok(Array4::from_shape_fn((1, 3, h, w), |(_, c, y, x)| {
        img.get_pixel(x as u32, y as u32)[c]
    }))
}

/// Writes a `1 x 3 x H x W` array (clamped to `[0, 1]`) as an 8-bit PNG.
fn write_png(path: &Path, x: ArrayView4<f32>) -> Result<(), Box<dyn Error>> {
    let (h, w) = (x.shape()[2], x.shape()[3]);
    let img = image::RgbImage::from_fn(w as u32, h as u32, |px, py| {
        image::Rgb(std::array::from_fn(|c| {
            (x[[0, c, py as usize, px as usize]].clamp(0.0, 1.0) * 255.0).round() as u8
        }))
    });
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
    }
    img.save(path)
        .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    Ok(())
}

/// Mean and standard deviation of all values, and the range of the per-channel means.
fn stats(x: &Array4<f32>) -> (f64, f64, f64, f64) {
    let n = x.len() as f64;
    let mean = x.iter().map(|&v| v as f64).sum::<f64>() / n;
    let var = x.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
    let per_channel = x
        .axis_iter(Axis(1))
        .map(|c| c.iter().map(|&v| v as f64).sum::<f64>() / c.len() as f64);
    let (lo, hi) = per_channel.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), m| {
        (lo.min(m), hi.max(m))
    });
    (mean, var.sqrt(), lo, hi)
}

fn run(args: &Args) -> Result<(), Box<dyn Error>> {
    let mut weights = NetWeights::default();
    for path in &args.weights {
        let w = load_weights(path)?;
        for (have, new, what) in [
            (weights.encoder.is_some(), w.encoder.is_some(), "an encoder"),
            (weights.decoder.is_some(), w.decoder.is_some(), "a decoder"),
        ] {
            if have && new {
                return Err(format!("{} holds {what} too: give only one", path.display()).into());
            }
        }
        weights.encoder = weights.encoder.or(w.encoder);
        weights.decoder = weights.decoder.or(w.decoder);
    }
    let Some(encoder) = weights.encoder else {
        return Err("no encoder among the weights".into());
    };
    let encoder = encoder.with_resolution(args.resolution);
    let image = load_image(&args.image, args.max_side)?;
    println!(
        "encoder: relu1_1..relu{}_1, widths {:?}, {:?} pooling, {:?}",
        encoder.depth(),
        encoder.widths(),
        encoder.pool_rounding(),
        args.resolution
    );
    println!("image:   {} {:?}", args.image.display(), image.shape());

    let start = Instant::now();
    let feats = encoder.forward(image.view())?;
    println!("encoded in {:.2} s", start.elapsed().as_secs_f64());
    for (k, f) in feats.iter().enumerate() {
        let (mean, std, lo, hi) = stats(f);
        let shape = format!("{:?}", f.shape());
        println!(
            "  relu{}_1  {shape:<20} mean {mean:>8.4}  std {std:>8.4}  \
             channel means {lo:.4} ..= {hi:.4}",
            k + 1,
        );
    }

    let Some(decoder) = weights.decoder else {
        println!("no decoder given: nothing decoded");
        return Ok(());
    };
    let decoder = decoder.with_resolution(args.resolution);
    // The decoder takes relu{depth}_1 of the encoder it inverts.
    let level = decoder.depth();
    let input = level
        .checked_sub(1)
        .and_then(|i| feats.get(i))
        .filter(|f| f.shape()[1] == decoder.in_channels())
        .ok_or_else(|| {
            format!(
                "the decoder takes relu{level}_1 with {} channels, which this encoder does not \
                 give (widths {:?})",
                decoder.in_channels(),
                encoder.widths()
            )
        })?;
    let start = Instant::now();
    let decoded = decoder.forward(input.view())?;
    println!(
        "decoded relu{level}_1 to {:?} in {:.2} s",
        decoded.shape(),
        start.elapsed().as_secs_f64()
    );
    // Pooling rounds odd sizes up (ceil mode) or down (floor mode), so the upsampled output may
    // be a few pixels larger or smaller than the input: crop a larger one to the input's size and
    // compare over the pixels both have.
    let (h, w) = (image.shape()[2], image.shape()[3]);
    let (dh, dw) = (decoded.shape()[2], decoded.shape()[3]);
    let (ch, cw) = (dh.min(h), dw.min(w));
    let decoded = decoded.slice(ndarray::s![.., .., ..ch, ..cw]).to_owned();
    if (ch, cw) != (dh, dw) {
        println!("  cropped to {ch}x{cw}");
    }
    let target = image.slice(ndarray::s![.., .., ..ch, ..cw]);
    let mse = decoded
        .iter()
        .zip(target.iter())
        .map(|(&a, &b)| (a.clamp(0.0, 1.0) as f64 - b as f64).powi(2))
        .sum::<f64>()
        / decoded.len() as f64;
    let region = if (ch, cw) == (h, w) {
        String::new()
    } else {
        format!(" (over the top-left {ch}x{cw} pixels)")
    };
    println!(
        "  reconstruction PSNR {:.2} dB{region}",
        -10.0 * mse.log10()
    );
    write_png(&args.out, decoded.view())?;
    println!("  wrote {}", args.out.display());
    Ok(())
}
