//! Per-channel colour statistics of images, and AdaIN applied to the pixels themselves.
//!
//! ```text
//! style_stats IMAGE                    mean and std of each RGB channel
//! style_stats CONTENT STYLE OUT.png    the same for both, then AdaIN(content, style) in RGB:
//!                                      the content recoloured to the style's statistics
//! ```
//!
//! Statistics follow the crate's convention (unbiased variance, `std = sqrt(var + 1e-5)`), over
//! values in `[0, 1]`. The AdaIN result is written clamped to `[0, 1]`; its statistics are
//! printed before and after clamping.

use std::path::Path;

use anyhow::{bail, Context, Result};
use ndarray::Array4;
use style::{adain, channel_stats};

const USAGE: &str = "usage: style_stats IMAGE\n       style_stats CONTENT STYLE OUT.png";

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.as_slice() {
        [image] => {
            print_stats(image, &load(Path::new(image))?)?;
        }
        [content, style, out] => {
            let c = load(Path::new(content))?;
            let s = load(Path::new(style))?;
            print_stats(content, &c)?;
            print_stats(style, &s)?;
            let result = adain(&c, &s).context("AdaIN of the content by the style")?;
            print_stats("AdaIN", &result)?;
            let clamped = result.mapv(|v| v.clamp(0.0, 1.0));
            print_stats("AdaIN, clamped", &clamped)?;
            save(Path::new(out), &clamped)?;
            println!("wrote {out}");
        }
        _ => bail!("{USAGE}"),
    }
    Ok(())
}

/// An image as `[1, 3, H, W]` RGB in `[0, 1]`.
fn load(path: &Path) -> Result<Array4<f32>> {
    let img = image::open(path)
        .with_context(|| format!("reading the image {}", path.display()))?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok(Array4::from_shape_fn(
        (1, 3, h as usize, w as usize),
        |(_, c, y, x)| img.get_pixel(x as u32, y as u32)[c] as f32 / 255.0,
    ))
}

fn save(path: &Path, x: &Array4<f32>) -> Result<()> {
    let (_, _, h, w) = x.dim();
    let mut bytes = Vec::with_capacity(h * w * 3);
    for y in 0..h {
        for px in 0..w {
            for c in 0..3 {
                bytes.push((x[[0, c, y, px]] * 255.0).round() as u8);
            }
        }
    }
    image::save_buffer(path, &bytes, w as u32, h as u32, image::ColorType::Rgb8)
        .with_context(|| format!("writing {}", path.display()))
}

fn print_stats(name: &str, x: &Array4<f32>) -> Result<()> {
    let s = channel_stats(x).with_context(|| format!("statistics of {name}"))?;
    let (_, _, h, w) = x.dim();
    println!("{name} ({w}x{h})");
    for (c, label) in ["R", "G", "B"].iter().enumerate() {
        println!(
            "  {label}  mean {:.4}  std {:.4}",
            s.mean[[0, c]],
            s.std[[0, c]]
        );
    }
    Ok(())
}
