//! `dsgs stylize` on a tiny bundle (1,500 real Gaussians, random features and lifter, the real
//! relu3_1 WCT networks) at 64x64: frames, GIFs and the contact sheet, and bad input.

mod common;

use std::io::Cursor;

use common::{dsgs, fails, ok, save_tiny_bundle, scratch, size_of};
use dsgs_testkit::shared_path;
use image::AnimationDecoder;

fn styles() -> [std::path::PathBuf; 2] {
    [
        shared_path("data/styles/mondrian.jpg"),
        shared_path("data/styles/small-set/3.jpg"),
    ]
}

#[test]
fn two_styles_give_frames_gifs_and_a_contact_sheet() {
    let dir = scratch("stylize-two");
    let bundle = save_tiny_bundle(&dir);
    let out = dir.join("out");
    let [a, b] = styles();
    ok(dsgs()
        .arg("stylize")
        .arg(&bundle)
        .arg("--style")
        .arg(&a)
        .arg("--style")
        .arg(&b)
        .args([
            "--style-size",
            "96",
            "--cameras",
            "path",
            "--frames",
            "5",
            "--gif",
            "-o",
        ])
        .arg(&out));
    for name in ["mondrian", "3"] {
        for i in 0..5 {
            let f = out.join(name).join(format!("frame_{i:04}.png"));
            assert_eq!(size_of(&f), (64, 64), "{}", f.display());
        }
        assert!(!out.join(name).join("frame_0005.png").exists());
        let gif = std::fs::read(out.join(format!("{name}.gif"))).unwrap();
        let frames = image::codecs::gif::GifDecoder::new(Cursor::new(gif))
            .unwrap()
            .into_frames()
            .collect_frames()
            .unwrap();
        assert_eq!(frames.len(), 5);
        assert_eq!(frames[0].buffer().dimensions(), (64, 64));
    }
    // Rows: the colour render and the two styles; columns: the style and 4 of the 5 views.
    assert_eq!(size_of(&out.join("contact_sheet.png")), (5 * 64, 3 * 64));
    // The two styles differ.
    let fa = image::open(out.join("mondrian/frame_0002.png"))
        .unwrap()
        .to_rgb8();
    let fb = image::open(out.join("3/frame_0002.png")).unwrap().to_rgb8();
    assert_ne!(fa.into_raw(), fb.into_raw());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn weighted_styles_mix_into_one_output() {
    let dir = scratch("stylize-mix");
    let bundle = save_tiny_bundle(&dir);
    let out = dir.join("out");
    let [a, b] = styles();
    ok(dsgs()
        .arg("stylize")
        .arg(&bundle)
        .arg("--style")
        .arg(&a)
        .arg("--style")
        .arg(&b)
        .args(["--mix", "0.25,0.75", "--alpha", "0.8", "--preserve-colour"])
        .args(["--style-size", "64", "--cameras", "test", "-o"])
        .arg(&out));
    // Two held-out cameras (orbit views 0 and 8 of 16).
    assert_eq!(size_of(&out.join("mix/frame_0001.png")), (64, 64));
    assert!(!out.join("mix/frame_0002.png").exists());
    assert!(!out.join("mondrian").exists());
    assert_eq!(size_of(&out.join("contact_sheet.png")), (3 * 64, 2 * 64));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_stylize_input_is_refused_with_a_message() {
    let dir = scratch("stylize-bad");
    let bundle = save_tiny_bundle(&dir);
    let [a, _] = styles();
    let base = |out: &str| {
        let mut c = dsgs();
        c.arg("stylize")
            .arg(&bundle)
            .args(["--frames", "2", "--style-size", "64", "-o"])
            .arg(dir.join(out));
        c
    };
    // A style file that is not an image.
    let text = dir.join("notes.jpg");
    std::fs::write(&text, "not an image at all").unwrap();
    let err = fails(base("o1").arg("--style").arg(&text));
    assert!(
        err.contains(&format!("style image {}: ", text.display()))
            && err.contains("cannot decode image"),
        "{err}"
    );
    assert_eq!(err.matches("notes.jpg").count(), 1, "{err}");
    // A missing style file.
    let err = fails(base("o2").args(["--style", "nowhere/style.png"]));
    assert!(err.contains("style image nowhere/style.png"), "{err}");
    // A decoder of another width (the compressed relu4_1 decoder takes 128 channels).
    let err = fails(
        base("o3")
            .arg("--style")
            .arg(&a)
            .arg("--decoder")
            .arg(shared_path("weights/compressed-16x-relu4_1/4SD.pth")),
    );
    assert!(
        err.contains("the decoder takes 128 channels") && err.contains("4SD.pth"),
        "{err}"
    );
    // A bundle directory that is not a bundle.
    let err = fails(
        dsgs()
            .arg("stylize")
            .arg(&dir)
            .arg("--style")
            .arg(&a)
            .arg("-o")
            .arg(dir.join("o4")),
    );
    assert!(err.contains("no bundle.json"), "{err}");
    assert!(!err.contains("os error"), "{err}");
    // A bundle folder that is not there.
    let gone = dir.join("gone");
    let err = fails(
        dsgs()
            .arg("stylize")
            .arg(&gone)
            .arg("--style")
            .arg(&a)
            .arg("-o")
            .arg(dir.join("o7")),
    );
    assert!(
        err.contains(&format!("bundle folder {} not found", gone.display())),
        "{err}"
    );
    assert!(!err.contains("os error"), "{err}");
    // Weights that do not match the styles.
    let err = fails(base("o5").arg("--style").arg(&a).args(["--mix", "1,2"]));
    assert!(err.contains("--mix has 2 values for 1 style"), "{err}");
    // MP4 without ffmpeg on PATH.
    let empty = dir.join("empty-path");
    std::fs::create_dir_all(&empty).unwrap();
    let err = fails(
        base("o6")
            .arg("--style")
            .arg(&a)
            .arg("--mp4")
            .env("PATH", &empty),
    );
    assert!(err.contains("ffmpeg"), "{err}");
    // A strength outside [0, 1] and weights that are all zero.
    let err = fails(base("o8").arg("--style").arg(&a).args(["--alpha", "5"]));
    assert!(err.contains("--alpha") && err.contains('5'), "{err}");
    let err = fails(
        base("o9")
            .arg("--style")
            .arg(&a)
            .arg("--style")
            .arg(&a)
            .args(["--mix", "0,0"]),
    );
    assert!(err.contains("--mix 0,0: the weights are all zero"), "{err}");
    // Nothing was written for any of the refused runs.
    for o in ["o1", "o2", "o3", "o4", "o5", "o6", "o7", "o8", "o9"] {
        assert!(!dir.join(o).exists(), "{o} was written");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_style_that_does_not_decode_fails_before_any_output() {
    let dir = scratch("stylize-garbage");
    let bundle = save_tiny_bundle(&dir);
    let [a, _] = styles();
    let garbage = dir.join("style.txt");
    std::fs::write(&garbage, "these are words, not pixels").unwrap();
    let out = dir.join("out");
    // The good style first: the bad one is still decoded before the first frame.
    let err = fails(
        dsgs()
            .arg("stylize")
            .arg(&bundle)
            .arg("--style")
            .arg(&a)
            .arg("--style")
            .arg(&garbage)
            .args(["--frames", "2", "--style-size", "64", "-o"])
            .arg(&out),
    );
    assert!(
        err.contains(&format!("style image {}: ", garbage.display())),
        "{err}"
    );
    assert!(!err.contains("dataset:"), "{err}");
    assert_eq!(err.matches("style.txt").count(), 1, "{err}");
    assert!(!out.exists(), "{} was written", out.display());
    std::fs::remove_dir_all(&dir).ok();
}
