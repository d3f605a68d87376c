//! PLY reading and writing: the real 3DGS output file (re-saved byte for byte, values checked
//! against an independent PLY reader, feature round trip), the hand-made ASCII and big-endian
//! fixtures (expected values written by hand from the fixture text), extra columns, and errors.

use std::path::{Path, PathBuf};

use dsgs_testkit::{repo_fixture, scratch_dir, shared_path};
use gaussian::ply::{
    encode_ply, load_ply, load_ply_with_extras, parse_ply, property_names, save_ply,
    save_ply_with_extras, ExtraProperty, PlyErrorKind, ScalarType,
};
use gaussian::FeatureGaussians;

fn trained() -> PathBuf {
    shared_path("data/gaussians/trained_9080.ply")
}

#[test]
fn trained_file_loads_and_resaves_byte_identically() {
    let path = trained();
    let scene = load_ply(&path).unwrap();
    assert_eq!(scene.len(), 9080);
    assert_eq!(scene.sh_degree, 3);
    assert_eq!(scene.feature_dim, 0);
    scene.validate().unwrap();

    let original = std::fs::read(&path).unwrap();
    let encoded = encode_ply(&scene, &[], &path).unwrap();
    assert_eq!(encoded.len(), original.len());
    assert!(encoded == original, "re-encoded bytes differ");

    let dir = scratch_dir("ply", "resave");
    let out = dir.join("point_cloud.ply");
    save_ply(&out, &scene).unwrap();
    assert!(
        std::fs::read(&out).unwrap() == original,
        "saved file differs"
    );
    // Only the destination is left in the directory (the temporary file was renamed).
    let entries: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().collect();
    assert_eq!(entries.len(), 1);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Compares every value with what the `ply-rs-bw` crate reads from the same file, mapping the
/// channel-major `f_rest` layout by hand: `f_rest_{c*15 + k-1}` is `sh[n*16 + k][c]`.
#[test]
fn trained_file_values_match_an_independent_reader() {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};

    let path = trained();
    let scene = load_ply(&path).unwrap();
    let mut f = std::fs::File::open(&path).unwrap();
    let ply = Parser::<DefaultElement>::new().read_ply(&mut f).unwrap();
    let vertices = &ply.payload["vertex"];
    assert_eq!(vertices.len(), scene.len());
    let get = |v: &DefaultElement, name: &str| match v.get(name) {
        Some(Property::Float(x)) => *x,
        other => panic!("property {name}: {other:?}"),
    };
    for (n, v) in vertices.iter().enumerate() {
        for a in 0..3 {
            assert_eq!(
                scene.means[n][a].to_bits(),
                get(v, ["x", "y", "z"][a]).to_bits()
            );
            assert_eq!(
                scene.log_scales[n][a].to_bits(),
                get(v, &format!("scale_{a}")).to_bits()
            );
            assert_eq!(
                scene.sh[n * 16][a].to_bits(),
                get(v, &format!("f_dc_{a}")).to_bits()
            );
        }
        for a in 0..4 {
            assert_eq!(
                scene.quats[n][a].to_bits(),
                get(v, &format!("rot_{a}")).to_bits()
            );
        }
        assert_eq!(
            scene.opacity_logits[n].to_bits(),
            get(v, "opacity").to_bits()
        );
        for c in 0..3 {
            for k in 1..16 {
                let file = get(v, &format!("f_rest_{}", c * 15 + k - 1));
                assert_eq!(
                    scene.sh[n * 16 + k][c].to_bits(),
                    file.to_bits(),
                    "n {n} k {k} c {c}"
                );
            }
        }
    }
}

#[test]
fn trained_file_round_trips_with_32_features() {
    let mut scene = load_ply(trained()).unwrap().with_features(32, 0.0);
    for (i, v) in scene.features.iter_mut().enumerate() {
        *v = ((i as f32) * 0.37).sin() * 3.0 - 0.5;
    }
    let dir = scratch_dir("ply", "features");
    let out = dir.join("features.ply");
    save_ply(&out, &scene).unwrap();
    let back = load_ply(&out).unwrap();
    assert_eq!(back.feature_dim, 32);
    assert!(
        back == scene,
        "scene with features did not round-trip exactly"
    );
    // The header names the feature columns after rot_3, and each vertex grew by 32 floats.
    let bytes = std::fs::read(&out).unwrap();
    let text = String::from_utf8_lossy(&bytes[..4000]).to_string();
    assert!(text.contains("property float rot_3\nproperty float f_feat_0\n"));
    assert!(text.contains("property float f_feat_31\nend_header\n"));
    let header_len = text.find("end_header\n").unwrap() + "end_header\n".len();
    assert_eq!(bytes.len() - header_len, 9080 * (62 + 32) * 4);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Expected values read off the fixture text by hand. `f_rest` is channel-major with K-1 = 3
/// rest coefficients per channel: `sh[k][c] = f_rest_{3c + k-1}`.
#[test]
fn ascii_fixture_with_shuffled_properties() {
    let s = load_ply_with_extras(repo_fixture("ply/tiny_ascii_deg1.ply")).unwrap();
    let g = &s.gaussians;
    assert_eq!(g.len(), 2);
    assert_eq!(g.sh_degree, 1);
    assert_eq!(g.feature_dim, 0);
    assert_eq!(g.means, vec![[10.0, 20.0, 30.0], [-1.0, -2.0, -3.0]]);
    assert_eq!(g.log_scales, vec![[-1.0, -2.0, -3.0], [0.0, 0.0, 0.0]]);
    assert_eq!(g.quats, vec![[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]]);
    assert_eq!(g.opacity_logits, vec![0.5, -1.5]);
    let expected: Vec<[f32; 3]> = vec![
        [1.0, 2.0, 3.0],
        [0.1, 0.4, 0.7],
        [0.2, 0.5, 0.8],
        [0.3, 0.6, 0.9],
        [-1.0, -2.0, -3.0],
        [-0.1, -0.4, -0.7],
        [-0.2, -0.5, -0.8],
        [-0.3, -0.6, -0.9],
    ];
    assert_eq!(g.sh, expected);
    // The uchar column is kept; the list column and the face element are dropped.
    assert_eq!(
        s.extras,
        vec![ExtraProperty {
            name: "red".into(),
            ty: ScalarType::U8,
            values: vec![255.0, 0.0],
        }]
    );
}

#[test]
fn big_endian_fixture_with_double_and_features() {
    let g = load_ply(repo_fixture("ply/tiny_be_deg0_feat2.ply")).unwrap();
    assert_eq!(g.len(), 2);
    assert_eq!(g.sh_degree, 0);
    assert_eq!(g.feature_dim, 2);
    assert_eq!(g.means, vec![[1.5, -2.25, 3.0], [-0.5, 0.0, 100.0]]);
    assert_eq!(g.sh, vec![[0.25, 0.5, 0.75], [-0.25, 0.0, 1.0]]);
    assert_eq!(g.opacity_logits, vec![2.0, -2.0]);
    assert_eq!(g.log_scales, vec![[-4.0, -5.0, -6.0], [1.0, 2.0, 3.0]]);
    assert_eq!(g.quats, vec![[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]);
    assert_eq!(g.features, vec![0.125, -8.0, 3.0, 4.0]);
}

#[test]
fn extra_columns_round_trip() {
    let s = load_ply_with_extras(repo_fixture("ply/tiny_ascii_deg1.ply")).unwrap();
    let dir = scratch_dir("ply", "extras");
    let out = dir.join("extras.ply");
    save_ply_with_extras(&out, &s.gaussians, &s.extras).unwrap();
    let back = load_ply_with_extras(&out).unwrap();
    assert_eq!(back, s);
    // An extra column that clashes with the layout, or has the wrong length, is refused.
    let clash = ExtraProperty {
        name: "opacity".into(),
        ty: ScalarType::F32,
        values: vec![0.0; 2],
    };
    let err = save_ply_with_extras(&out, &s.gaussians, &[clash]).unwrap_err();
    assert!(err.to_string().contains("clashes"), "{err}");
    let short = ExtraProperty {
        name: "w".into(),
        ty: ScalarType::F32,
        values: vec![0.0; 1],
    };
    assert!(save_ply_with_extras(&out, &s.gaussians, &[short]).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The byte position of each written value, computed from the documented layout by hand.
#[test]
fn writer_puts_f_rest_channel_major() {
    let k = 4; // degree 1
    let mut g = FeatureGaussians::<f64> {
        means: vec![[1.0, 2.0, 3.0]],
        log_scales: vec![[4.0, 5.0, 6.0]],
        quats: vec![[7.0, 8.0, 9.0, 10.0]],
        opacity_logits: vec![11.0],
        sh_degree: 1,
        sh: vec![[0.0; 3]; k],
        feature_dim: 0,
        features: vec![],
    };
    for (kk, row) in g.sh.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = 100.0 + 10.0 * kk as f64 + c as f64; // 1kc
        }
    }
    let bytes = encode_ply(&g, &[], Path::new("mem.ply")).unwrap();
    let names = property_names(1, 0);
    assert_eq!(names.len(), 6 + 3 + 9 + 1 + 3 + 4);
    let body = &bytes[bytes.len() - names.len() * 4..];
    let value = |name: &str| {
        let i = names.iter().position(|n| n == name).unwrap();
        f32::from_le_bytes(body[4 * i..4 * i + 4].try_into().unwrap())
    };
    assert_eq!(value("nx"), 0.0);
    assert_eq!(value("f_dc_2"), 102.0);
    // f_rest_{3c + k - 1}
    assert_eq!(value("f_rest_0"), 110.0);
    assert_eq!(value("f_rest_1"), 120.0);
    assert_eq!(value("f_rest_2"), 130.0);
    assert_eq!(value("f_rest_3"), 111.0);
    assert_eq!(value("f_rest_8"), 132.0);
    assert_eq!(value("opacity"), 11.0);
    assert_eq!(value("rot_3"), 10.0);
}

fn parse_err(text: &[u8]) -> String {
    match parse_ply(text, Path::new("bad.ply")) {
        Ok(_) => panic!("accepted: {}", String::from_utf8_lossy(text)),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.starts_with("bad.ply: "), "{msg}");
            msg
        }
    }
}

const GOOD_HEADER: &str = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\nproperty float opacity\nproperty float scale_0\nproperty float scale_1\nproperty float scale_2\nproperty float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\nend_header\n";

#[test]
fn malformed_files_give_precise_errors() {
    let good = format!("{GOOD_HEADER}1 2 3 4 5 6 7 8 9 10 11 12 13 14\n");
    let g = parse_ply(good.as_bytes(), Path::new("ok.ply"))
        .unwrap()
        .gaussians;
    assert_eq!(g.means, vec![[1.0, 2.0, 3.0]]);
    assert_eq!(g.quats, vec![[11.0, 12.0, 13.0, 14.0]]);

    let m = parse_err(format!("{GOOD_HEADER}1 2 3 4 5 6 7 8 9 10 11 12 13\n").as_bytes());
    assert!(
        m.contains("element `vertex` instance 0, property `rot_3`"),
        "{m}"
    );
    assert!(m.contains("truncated"), "{m}");

    let m = parse_err(format!("{GOOD_HEADER}1 2 3 4 5 6 seven 8 9 10 11 12 13 14\n").as_bytes());
    assert!(
        m.contains("property `opacity`") && m.contains("`seven`"),
        "{m}"
    );

    let m = parse_err(
        GOOD_HEADER
            .replace("property float opacity\n", "")
            .as_bytes(),
    );
    assert!(m.contains("`opacity` is missing"), "{m}");

    let rest: String = (0..10)
        .map(|i| format!("property float f_rest_{i}\n"))
        .collect();
    let m = parse_err(
        GOOD_HEADER
            .replace("end_header\n", &format!("{rest}end_header\n"))
            .as_bytes(),
    );
    assert!(m.contains("10 `f_rest_*` properties"), "{m}");

    let rest: String = (1..10)
        .map(|i| format!("property float f_rest_{i}\n"))
        .collect();
    let m = parse_err(
        GOOD_HEADER
            .replace("end_header\n", &format!("{rest}end_header\n"))
            .as_bytes(),
    );
    assert!(m.contains("f_rest_9"), "{m}");

    let m = parse_err(b"PLY\nformat ascii 1.0\nend_header\n");
    assert!(m.contains("magic"), "{m}");
    let m = parse_err(b"ply\nformat binary_middle_endian 1.0\nend_header\n");
    assert!(
        m.contains("header line 2") && m.contains("unknown format"),
        "{m}"
    );
    let m = parse_err(GOOD_HEADER.replace("float y", "quad y").as_bytes());
    assert!(m.contains("unknown property type `quad`"), "{m}");
    let m = parse_err(GOOD_HEADER.replace("float y", "float x").as_bytes());
    assert!(m.contains("declared twice"), "{m}");
    let m = parse_err(&GOOD_HEADER.as_bytes()[..100]);
    assert!(m.contains("before `end_header`"), "{m}");
    let m = parse_err(
        GOOD_HEADER
            .replace("float x", "list uchar float x")
            .as_bytes(),
    );
    assert!(m.contains("`x` is a list"), "{m}");
}

#[test]
fn absurd_counts_are_rejected_before_allocating() {
    for count in ["4000000000", "18446744073709551615"] {
        let text = GOOD_HEADER
            .replace("format ascii", "format binary_little_endian")
            .replace("vertex 1", &format!("vertex {count}"));
        let m = parse_err(text.as_bytes());
        assert!(
            m.contains("element `vertex`") && m.contains("declares"),
            "{m}"
        );
    }
    let m = parse_err(GOOD_HEADER.replace("vertex 1", "vertex 1e9").as_bytes());
    assert!(m.contains("invalid count"), "{m}");
    // An element without properties reads nothing, whatever its count.
    let text = GOOD_HEADER.replace(
        "end_header\n",
        "element empty 18446744073709551615\nend_header\n",
    );
    let ok = format!("{text}1 2 3 4 5 6 7 8 9 10 11 12 13 14\n");
    assert_eq!(
        parse_ply(ok.as_bytes(), Path::new("x"))
            .unwrap()
            .gaussians
            .len(),
        1
    );
}

#[test]
fn non_finite_values_are_reported() {
    let text = format!("{GOOD_HEADER}1 2 nan 4 5 6 7 8 9 10 11 12 13 14\n");
    let m = parse_err(text.as_bytes());
    assert!(m.contains("non-finite") && m.contains("means"), "{m}");
}

#[test]
fn io_errors_name_the_file() {
    let missing = Path::new("/nonexistent-dir/none.ply");
    let err = load_ply(missing).unwrap_err();
    assert!(matches!(err.kind, PlyErrorKind::Io(_)));
    assert!(err.to_string().contains("none.ply"));
    let g = load_ply(repo_fixture("ply/tiny_be_deg0_feat2.ply")).unwrap();
    // A directory that cannot be created (a regular file is in the way), whoever runs the test.
    let file = std::env::temp_dir().join(format!("dsgs-ply-blocker-{}", std::process::id()));
    std::fs::write(&file, b"not a directory").unwrap();
    let blocked = file.join("none.ply");
    let err = save_ply(&blocked, &g).unwrap_err();
    std::fs::remove_file(&file).unwrap();
    assert!(matches!(err.kind, PlyErrorKind::Io(_)));
    assert!(
        err.to_string().starts_with(&blocked.display().to_string()),
        "{err}"
    );
}
