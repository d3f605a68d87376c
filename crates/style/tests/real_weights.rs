//! Stylization with the real pretrained networks of the shared `weights/` directory, against
//! PyTorch's outputs (`oracle/fixtures/real_weights.safetensors`, float32): the WCT relu3_1 pair
//! (standard and fullres) and the 16x-compressed relu4_1 pair. Also: the style transform folded
//! into the real decoder, and a stylized PNG of the full photo for inspection.
//!
//! Tolerance 1e-4 relative: the reference is float64 rounded to float32 (6e-8), and our `f32`
//! path (up to 14 convolutions with dot products of up to 2304 terms, plus the AdaIN
//! normalisation) is accurate to about 1e-6 here; a margin of a hundred remains.

mod common;

use std::path::Path;

use common::*;
use dsgs_testkit::arrays::hwc_image;
use dsgs_testkit::oracle::real_weights_fixture;
use dsgs_testkit::{shared_path, Fixture};
use ndarray::Array4;
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, Resolution};
use style::*;

const TOL: f64 = 1e-4;

fn wct_pair() -> (Encoder, Decoder) {
    let sd = |rel: &str| load_checkpoint(&shared_path(&format!("weights/{rel}"))).unwrap();
    (
        Encoder::from_state_dict(&sd("wct-relu1_1-3_1/vgg_normalised_conv3_1.pth")).unwrap(),
        Decoder::from_state_dict(&sd("wct-relu1_1-3_1/feature_invertor_conv3_1.pth")).unwrap(),
    )
}

fn check(r: &mut Report, key: &str, a: &Array4<f32>, fx: &Fixture) {
    r.add(key, rel_err(a, fx.get(key)));
}

#[test]
fn wct_relu3_1_stylization_matches_pytorch() {
    let fx = real_weights_fixture();
    let (enc, dec) = wct_pair();
    let (content, style_img) = (hwc_image(fx.get("content")), hwc_image(fx.get("style")));
    let mut r = Report::default();
    for (v, res) in [
        ("standard", Resolution::Standard),
        ("fullres", Resolution::Fullres),
    ] {
        let (enc, dec) = (
            enc.clone().with_resolution(res),
            dec.clone().with_resolution(res),
        );
        let s = encode_style(&enc, &style_img).unwrap();
        // The cache encodes once per (encoder, image) and hands out the same statistics.
        let cache = StyleCache::new();
        for _ in 0..2 {
            assert_eq!(*cache.get_or_encode(v, &enc, &style_img).unwrap(), s);
        }
        assert_eq!(cache.counts(), (1, 1));
        let c3 = enc.forward(content.view()).unwrap().pop().unwrap();
        check(
            &mut r,
            &format!("wct.{v}.adain"),
            &adain_with_stats(&c3, s.deepest()).unwrap(),
            &fx,
        );
        let out = stylize(&enc, &dec, &content, s.deepest(), 1.0).unwrap();
        check(&mut r, &format!("wct.{v}.stylized"), &out, &fx);
        // The same through the style cache and image-level entry point.
        let again = stylize_image(&enc, &dec, &content, &style_img, 1.0, false).unwrap();
        assert_eq!(again, out);
    }
    r.check("real", TOL);
}

#[test]
fn compressed_relu4_1_stylization_matches_pytorch() {
    let fx = real_weights_fixture();
    let sd = |rel: &str| load_checkpoint(&shared_path(&format!("weights/{rel}"))).unwrap();
    let enc: Encoder = Encoder::from_state_dict(&sd("compressed-16x-relu4_1/4SE.pth")).unwrap();
    let dec: Decoder = Decoder::from_state_dict(&sd("compressed-16x-relu4_1/4SD.pth")).unwrap();
    let s = encode_style(&enc, &hwc_image(fx.get("style"))).unwrap();
    assert_eq!(s.levels.len(), 4);
    let out = stylize(&enc, &dec, &hwc_image(fx.get("content")), s.deepest(), 1.0).unwrap();
    let mut r = Report::default();
    check(&mut r, "compressed.stylized", &out, &fx);
    r.check("real", TOL);
}

/// Folding `T_s` into the first decoder conv renders the same image as the separate transform.
/// Tolerance 1e-5 relative: both paths are `f32`; they differ by the rounding of the folded
/// weights and bias (relative 6e-8 each) propagated through the decoder, about 1e-6.
#[test]
fn folded_real_decoder_equals_the_unfolded_path() {
    let fx = real_weights_fixture();
    let (enc, dec) = wct_pair();
    for res in [Resolution::Standard, Resolution::Fullres] {
        let (enc, dec) = (
            enc.clone().with_resolution(res),
            dec.clone().with_resolution(res),
        );
        let s = encode_style(&enc, &hwc_image(fx.get("style"))).unwrap();
        let y = instance_normalize(
            &enc.forward(hwc_image(fx.get("content")).view())
                .unwrap()
                .pop()
                .unwrap(),
        )
        .unwrap();
        let unfolded = dec
            .forward(style_transform(&y, s.deepest()).unwrap().view())
            .unwrap();
        let folded = fold_style_transform(&dec, s.deepest())
            .unwrap()
            .forward(y.view())
            .unwrap();
        let err = rel_err_arr(&folded, &unfolded.mapv(|v| v as f64));
        println!("folded vs unfolded ({res:?}): {err:.2e}");
        assert!(err <= 1e-5, "folded decoder differs by {err:.3e}");
    }
    // A wrong width or a batch of styles is refused.
    let s2 = ChannelStats::<f32>::zeros(2, 256);
    assert!(fold_style_transform(&dec, &s2).is_err());
    assert!(fold_style_transform(&dec, &ChannelStats::<f32>::zeros(1, 3)).is_err());
}

/// An image resized to `short_side` pixels on its short side and a multiple of 4 on the long
/// side (the standard relu3_1 networks pool twice, so only such sizes decode to the same size).
fn load_rgb(path: &Path, short_side: u32) -> Array4<f32> {
    let img = image::open(path).unwrap().to_rgb8();
    let (w, h) = img.dimensions();
    let long =
        |a: u32, b: u32| ((a as f64 * short_side as f64 / b as f64) / 4.0).round() as u32 * 4;
    let (nw, nh) = if w < h {
        (short_side, long(h, w))
    } else {
        (long(w, h), short_side)
    };
    let img = image::imageops::resize(&img, nw, nh, image::imageops::FilterType::Triangle);
    Array4::from_shape_fn((1, 3, nh as usize, nw as usize), |(_, c, y, x)| {
        img.get_pixel(x as u32, y as u32)[c] as f32 / 255.0
    })
}

fn save_png(img: &Array4<f32>, path: &Path) {
    let (_, _, h, w) = img.dim();
    let out =
        image::RgbImage::from_fn(w as u32, h as u32, |x, y| {
            image::Rgb([0, 1, 2].map(|c| {
                (img[[0, c, y as usize, x as usize]].clamp(0.0, 1.0) * 255.0).round() as u8
            }))
        });
    out.save(path).unwrap();
}

/// Stylizes chicago.jpg with brushstrokes.jpg (256 pixels on the short side) with the real WCT
/// relu3_1 pair, plain and with the content's colours preserved, and writes the PNGs for
/// inspection. Checks what can be checked without a reference: the output's shape and range, and
/// that the stylized image's colour statistics moved towards the style's.
#[test]
fn stylized_photo_is_written() {
    let (enc, dec) = wct_pair();
    let data = dsgs_testkit::shared_dir().join("data");
    let content = load_rgb(&data.join("content/chicago.jpg"), 256);
    let style_img = load_rgb(&data.join("styles/brushstrokes.jpg"), 256);
    let out = stylize_image(&enc, &dec, &content, &style_img, 1.0, false).unwrap();
    let kept = stylize_image(&enc, &dec, &content, &style_img, 1.0, true).unwrap();
    assert_eq!(out.dim(), content.dim());
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"));
    save_png(&content, &dir.join("chicago_256.png"));
    save_png(&out, &dir.join("chicago_brushstrokes.png"));
    save_png(&kept, &dir.join("chicago_brushstrokes_keep_colour.png"));
    println!("wrote {}", dir.join("chicago_brushstrokes.png").display());
    let inside = out.iter().filter(|v| (-0.1..=1.1).contains(*v)).count() as f64 / out.len() as f64;
    assert!(
        inside > 0.99,
        "only {inside:.3} of the pixels are near [0, 1]"
    );
    let mean = |a: &Array4<f32>| channel_stats(a).unwrap().mean;
    let (mc, ms, mo, mk) = (mean(&content), mean(&style_img), mean(&out), mean(&kept));
    let dist =
        |a: &ndarray::Array2<f32>, b: &ndarray::Array2<f32>| (a - b).mapv(|v| v * v).sum().sqrt();
    println!("colour means: content {mc:?}, style {ms:?}, stylized {mo:?}, colour kept {mk:?}");
    assert!(
        dist(&mo, &ms) < dist(&mc, &ms),
        "the stylized colours did not move towards the style"
    );
    assert!(
        dist(&mk, &mc) < dist(&mo, &mc),
        "colour preservation did not keep the content's colours"
    );
}
