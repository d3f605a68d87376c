//! `dsgs stylize-image`: 2D stylization of photos with real networks (the WCT relu2_1 pair, small
//! enough to be quick), checked by properties of the method rather than by recorded numbers.

mod common;

use common::{dsgs, fails, ok, scratch, size_of};
use dsgs_testkit::shared_path;
use serde_json::Value;

fn networks() -> [String; 4] {
    let w = |f: &str| {
        shared_path(&format!("weights/wct-relu1_1-3_1/{f}"))
            .display()
            .to_string()
    };
    [
        "--encoder".into(),
        w("vgg_normalised_conv2_1.pth"),
        "--decoder".into(),
        w("feature_invertor_conv2_1.pth"),
    ]
}

fn psnr(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    let n = a.as_raw().len() as f64;
    let mse: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum::<f64>()
        / n;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

#[test]
fn photos_are_stylized_measured_and_laid_out() {
    let dir = scratch("stylize-image");
    let out = dir.join("out");
    let photos = [
        shared_path("data/content/sailboat.jpg"),
        shared_path("data/content/chicago.jpg"),
    ];
    let styles = [
        shared_path("data/styles/mondrian.jpg"),
        shared_path("data/styles/sketch.png"),
    ];
    // The two photos with the two styles and their mixture (1, 0) at 64 pixels, into `out`.
    let stylize = |extra: &[&std::ffi::OsStr], out: &std::path::Path| {
        ok(dsgs()
            .arg("stylize-image")
            .args(&photos)
            .arg("--style")
            .arg(&styles[0])
            .arg("--style")
            .arg(&styles[1])
            .args(networks())
            .args(["--content-size", "64", "--style-size", "64", "--mix", "1,0"])
            .args(extra)
            .args(["--no-progress", "-o"])
            .arg(out));
    };
    stylize(&[], &out);
    let report: Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let pairs = report["pairs"].as_array().unwrap();
    // Two photos times two styles and the mixture, photo by photo.
    assert_eq!(pairs.len(), 6);
    let names: Vec<&str> = pairs.iter().map(|p| p["style"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        ["mondrian", "sketch", "mix", "mondrian", "sketch", "mix"]
    );
    for p in pairs {
        for key in ["style_loss", "texture_distance", "content_loss"] {
            let v = p[key].as_f64().unwrap();
            assert!(v.is_finite() && v > 0.0, "{key} {v} in {p}");
        }
        let (w, h) = size_of(&out.join(p["file"].as_str().unwrap()));
        assert_eq!(w.max(h), 64, "{p}");
    }
    // Two different paintings give the photos textures a positive distance apart; one painting
    // given twice gives the same outputs, no distance at all.
    assert!(report["mean_texture_between"].as_f64().unwrap() > 0.0);
    let twice = dir.join("twice");
    ok(dsgs()
        .arg("stylize-image")
        .arg(&photos[0])
        .arg("--style")
        .arg(&styles[0])
        .arg("--style")
        .arg(&styles[0])
        .args(networks())
        .args([
            "--content-size",
            "64",
            "--style-size",
            "64",
            "--no-progress",
            "-o",
        ])
        .arg(&twice));
    let r: Value =
        serde_json::from_slice(&std::fs::read(twice.join("report.json")).unwrap()).unwrap();
    assert_eq!(r["mean_texture_between"].as_f64(), Some(0.0), "{r}");
    // A mixture with weights (1, 0) is the first style exactly (the transform is affine in
    // the statistics).
    let read = |f: &str| std::fs::read(out.join(f)).unwrap();
    assert_eq!(read("sailboat__mix.png"), read("sailboat__mondrian.png"));
    // The sheet: a header row of styles over one row per photo, 1 + 2 + 1 cells wide.
    let (sw, sh) = size_of(&out.join("contact_sheet.png"));
    let (cw, ch) = size_of(&out.join("sailboat__mondrian.png"));
    assert_eq!((sw, sh), (4 * cw, 3 * ch));

    // Measured with the stylizing encoder's own file: the same outputs and measures; measured
    // with a deeper encoder (relu3_1): the same outputs, other measures, and the report says so.
    let measured = |name: &str, encoder: std::path::PathBuf| {
        let dir = dir.join(name);
        stylize(&["--measure-with".as_ref(), encoder.as_os_str()], &dir);
        let r: Value =
            serde_json::from_slice(&std::fs::read(dir.join("report.json")).unwrap()).unwrap();
        assert_eq!(
            r["measured_with"].as_str().unwrap(),
            encoder.display().to_string()
        );
        assert_eq!(
            std::fs::read(dir.join("chicago__sketch.png")).unwrap(),
            read("chicago__sketch.png")
        );
        r
    };
    let wct = |f: &str| shared_path(&format!("weights/wct-relu1_1-3_1/{f}"));
    let same = measured("same", wct("vgg_normalised_conv2_1.pth"));
    let deeper = measured("deeper", wct("vgg_normalised_conv3_1.pth"));
    assert_eq!(
        report["measured_with"].as_str().unwrap(),
        "stylizing encoder"
    );
    for (i, p) in pairs.iter().enumerate() {
        for key in ["style_loss", "texture_distance", "content_loss"] {
            assert_eq!(same["pairs"][i][key], p[key], "{key} of {p}");
            let d = deeper["pairs"][i][key].as_f64().unwrap();
            assert!(d.is_finite() && d > 0.0, "{key} {d}");
            assert_ne!(deeper["pairs"][i][key], p[key], "{key} of {p}");
        }
    }

    // Strength 0 is the decoder's reconstruction of the photo, which this reconstruction
    // decoder makes close to the photo; the full style is further away.
    let zero = dir.join("zero");
    ok(dsgs()
        .arg("stylize-image")
        .arg(&photos[0])
        .arg("--style")
        .arg(&styles[0])
        .args(networks())
        .args(["--content-size", "64", "--style-size", "64", "--alpha", "0"])
        .args(["--no-progress", "-o"])
        .arg(&zero));
    let photo = image::open(&photos[0]).unwrap().to_rgb8();
    let load = |p: std::path::PathBuf| image::open(p).unwrap().to_rgb8();
    let rec = load(zero.join("sailboat__mondrian.png"));
    let styled = load(out.join("sailboat__mondrian.png"));
    let small = image::imageops::resize(
        &photo,
        rec.width(),
        rec.height(),
        image::imageops::FilterType::Triangle,
    );
    let (p0, p1) = (psnr(&rec, &small), psnr(&styled, &small));
    assert!(
        p0 > 20.0 && p0 > p1 + 3.0,
        "alpha 0: {p0} dB, alpha 1: {p1} dB"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn missing_inputs_are_named() {
    let dir = scratch("stylize-image-missing");
    let err = fails(
        dsgs()
            .arg("stylize-image")
            .arg(shared_path("data/content/sailboat.jpg"))
            .arg("--style")
            .arg(dir.join("no-such-folder"))
            .args(networks())
            .arg("-o")
            .arg(dir.join("out")),
    );
    assert!(
        err.contains("no-such-folder") && err.contains("no such file"),
        "{err}"
    );
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let err = fails(
        dsgs()
            .arg("stylize-image")
            .arg(&empty)
            .arg("--style")
            .arg(shared_path("data/styles/mondrian.jpg"))
            .args(networks())
            .arg("-o")
            .arg(dir.join("out")),
    );
    assert!(
        err.contains("empty") && err.contains("no .png or .jpg"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
