//! `dsgs weights`: import of PyTorch checkpoints into canonical safetensors, and bad input.

use std::process::Command;

use dsgs_testkit::shared_path;

fn dsgs() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dsgs"))
}

#[test]
fn import_then_info_describes_the_pair() {
    let out = std::env::temp_dir().join(format!("dsgs-weights-{}.safetensors", std::process::id()));
    let status = dsgs()
        .args(["weights", "import", "--encoder"])
        .arg(shared_path("oracle/fixtures/vgg_legacy.pth"))
        .arg("--decoder")
        .arg(shared_path("oracle/fixtures/decoder_zip.pth"))
        .arg("--output")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let info = dsgs().args(["weights", "info"]).arg(&out).output().unwrap();
    std::fs::remove_file(&out).ok();
    assert!(info.status.success());
    let text = String::from_utf8(info.stdout).unwrap();
    // the fixtures are the AdaIN layout at 1/8 width: VGG to relu5_1 (64/128/256/512/512 / 8)
    assert!(text.contains("canonical dsgs weights"), "{text}");
    assert!(
        text.contains("widths relu1_1..: 8, 16, 32, 64, 64"),
        "{text}"
    );
    assert!(text.contains("decoder: 64 -> 3 channels"), "{text}");
}

#[test]
fn a_non_checkpoint_fails_with_a_message_naming_the_file() {
    let style = shared_path("data/styles/mondrian.jpg");
    let out = dsgs()
        .args(["weights", "info"])
        .arg(&style)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("mondrian.jpg") && err.contains("not a PyTorch checkpoint"),
        "{err}"
    );
}

#[test]
fn a_mismatched_pair_is_refused() {
    let out = dsgs()
        .args(["weights", "import", "--encoder"])
        .arg(shared_path("weights/compressed-16x-relu4_1/4SE.pth"))
        .arg("--decoder")
        .arg(shared_path(
            "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
        ))
        .args(["--output", "/dev/null/never"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("not a pair"));
}

/// One network of a canonical pair is written alone: `--decoder PAIR.safetensors` keeps its
/// decoder and no encoder; a file without the network asked for is named.
#[test]
fn import_takes_one_network_of_a_canonical_pair() {
    let dir = std::env::temp_dir().join(format!("dsgs-weights-one-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let pair = dir.join("pair.safetensors");
    let run = |args: &[&std::ffi::OsStr]| dsgs().args(["weights", "import"]).args(args).output();
    let pair_out = run(&[
        "--encoder".as_ref(),
        shared_path("oracle/fixtures/vgg_legacy.pth").as_os_str(),
        "--decoder".as_ref(),
        shared_path("oracle/fixtures/decoder_zip.pth").as_os_str(),
        "-o".as_ref(),
        pair.as_os_str(),
    ])
    .unwrap();
    assert!(pair_out.status.success());
    let alone = dir.join("decoder.safetensors");
    let out = run(&[
        "--decoder".as_ref(),
        pair.as_os_str(),
        "-o".as_ref(),
        alone.as_os_str(),
    ])
    .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("decoder: 64 -> 3 channels"), "{text}");
    assert!(!text.contains("encoder:"), "{text}");
    // The decoder-only file has no encoder to give.
    let out = run(&[
        "--encoder".as_ref(),
        alone.as_os_str(),
        "-o".as_ref(),
        dir.join("x.safetensors").as_os_str(),
    ])
    .unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    std::fs::remove_dir_all(&dir).ok();
    assert!(!out.status.success());
    assert!(
        err.contains("decoder.safetensors holds a decoder, not an encoder"),
        "{err}"
    );
}
