//! Building networks from state dicts (layout detection and its errors) and the canonical
//! safetensors weights file (round trip and its errors).

mod common;

use std::path::PathBuf;

use common::*;
use dsgs_testkit::Fixture;
use nets::{
    Decoder, Encoder, Layout, Lifter, NetError, NetWeights, PoolRounding, Resolution, StateDict,
    TensorF32,
};

/// A scratch directory removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(test: &str) -> TempDir {
        let dir = std::env::temp_dir().join(format!("nets-test-{}-{test}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }

    fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn adain_state_dicts() -> (StateDict, StateDict) {
    let fx = nets_fixture();
    (state_dict(&fx, "vgg."), state_dict(&fx, "decoder."))
}

#[test]
fn the_f32_checkpoint_tensors_are_the_fixture_weights_rounded() {
    let ck = Fixture::shared("oracle/fixtures/checkpoints.safetensors");
    let (vgg, dec) = adain_state_dicts();
    assert_eq!(state_dict(&ck, "vgg."), vgg);
    assert_eq!(state_dict(&ck, "decoder."), dec);
    assert_eq!(
        nets::layout::detect_layout(&vgg).unwrap(),
        Layout::Sequential
    );
}

#[test]
fn canonical_file_round_trips() {
    let tmp = TempDir::new("canonical_file_round_trips");
    let (vgg, dec) = adain_state_dicts();
    let fx = nets_fixture();
    let encoder = Encoder::from_state_dict(&vgg)
        .unwrap()
        .with_depth(4)
        .unwrap();
    let decoder = Decoder::from_state_dict(&dec).unwrap();
    let lifter = Lifter::new(
        arr4::<f32>(fx.get("lifter.weight")),
        fx.get("lifter.bias").to_f32().into(),
    )
    .unwrap();
    let weights = NetWeights {
        encoder: Some(encoder.clone()),
        decoder: Some(decoder.clone()),
        lifter: Some(lifter),
    };
    let path = tmp.path("adain.safetensors");
    weights.save(&path).unwrap();
    let back = NetWeights::load(&path).unwrap();
    assert_eq!(back.to_state_dict(), weights.to_state_dict());
    assert_eq!(back.metadata(), weights.metadata());
    let md = weights.metadata();
    assert_eq!(md["encoder.widths"], "8,16,32,64");
    assert_eq!(md["encoder.convs_per_level"], "2,2,4,1");
    assert_eq!(md["encoder.pool"], "ceil");
    assert_eq!(md["decoder.final_relu"], "false");
    assert_eq!(md["decoder.convs_per_level"], "1,4,2,2");
    let sd = weights.to_state_dict();
    for name in [
        "encoder.conv0.weight",
        "encoder.conv1_1.weight",
        "encoder.conv3_4.bias",
        "encoder.conv4_1.weight",
        "decoder.conv4_1.weight",
        "decoder.conv1_1.bias",
        "lifter.weight",
    ] {
        assert!(sd.contains_key(name), "missing {name}");
    }
    assert!(
        !sd.contains_key("encoder.conv4_2.weight"),
        "only the convs that run are stored"
    );
    // Same outputs from the reloaded networks, standard and fullres.
    let x = arr4::<f32>(fx.get("content"));
    for res in [Resolution::Standard, Resolution::Fullres] {
        let a = encoder
            .clone()
            .with_resolution(res)
            .forward(x.view())
            .unwrap();
        let b = back
            .encoder
            .clone()
            .unwrap()
            .with_resolution(res)
            .forward(x.view())
            .unwrap();
        assert_eq!(a, b);
        let t = a[3].view();
        let da = decoder.clone().with_resolution(res).forward(t).unwrap();
        let db = back
            .decoder
            .clone()
            .unwrap()
            .with_resolution(res)
            .forward(t)
            .unwrap();
        assert_eq!(da, db);
    }
    // Saving again replaces the file atomically and leaves no temporary file behind.
    weights.save(&path).unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(path.parent().unwrap())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp"))
        .collect();
    assert!(leftovers.is_empty());
}

/// The compressed pair's named layout: `*_aux` ignored, floor pooling, final ReLU, and both flags
/// survive the canonical file.
#[test]
fn named_layout_and_its_flags_round_trip() {
    let tmp = TempDir::new("named_layout_and_its_flags_round_trip");
    let mut rng = TestRng::new(3);
    let mut e = StateDict::new();
    rng.conv_into(&mut e, "conv0", 3, 3, 1);
    for (name, o, c) in [("conv11", 4, 3), ("conv12", 4, 4), ("conv21", 6, 4)] {
        rng.conv_into(&mut e, name, o, c, 3);
    }
    rng.conv_into(&mut e, "conv21_aux", 16, 6, 1);
    let mut d = StateDict::new();
    for (name, o, c) in [("conv21", 4, 6), ("conv12", 4, 4), ("conv11", 3, 4)] {
        rng.conv_into(&mut d, name, o, c, 3);
    }
    assert_eq!(nets::layout::detect_layout(&e).unwrap(), Layout::Named);
    let enc: Encoder = Encoder::from_state_dict(&e).unwrap();
    let dec: Decoder = Decoder::from_state_dict(&d).unwrap();
    assert_eq!(enc.pool_rounding(), PoolRounding::Floor);
    assert_eq!(enc.widths(), vec![4, 6]);
    assert!(dec.final_relu());
    assert_eq!(
        dec.layers().map(|l| l.name.as_str()).collect::<Vec<_>>(),
        ["conv2_1", "conv1_2", "conv1_1"]
    );
    // The final ReLU is applied: no negative output.
    let x = TestRng::new(4).array4((1, 6, 3, 3)).mapv(|v| v as f32);
    assert!(dec.forward(x.view()).unwrap().iter().all(|&v| v >= 0.0));
    let path = tmp.path("named.safetensors");
    NetWeights {
        encoder: Some(enc.clone()),
        decoder: Some(dec.clone()),
        lifter: None,
    }
    .save(&path)
    .unwrap();
    let back = NetWeights::load(&path).unwrap();
    let (e2, d2) = (back.encoder.unwrap(), back.decoder.unwrap());
    assert_eq!(e2.pool_rounding(), PoolRounding::Floor);
    assert!(d2.final_relu());
    assert!(back.lifter.is_none());
    let img = TestRng::new(5).array4((1, 3, 9, 7)).mapv(|v| v as f32);
    assert_eq!(
        enc.forward(img.view()).unwrap(),
        e2.forward(img.view()).unwrap()
    );
    assert_eq!(
        dec.forward(x.view()).unwrap(),
        d2.forward(x.view()).unwrap()
    );
}

/// A named layout whose levels do not start at 1 (a `conv01` or `conv0_1` level 0) is a
/// layout error naming the layer, in the decoder and the encoder alike.
#[test]
fn a_level_numbered_zero_is_a_layout_error() {
    for names in [["conv01", "conv11"], ["conv0_1", "conv1_1"]] {
        let mut rng = TestRng::new(6);
        let mut d = StateDict::new();
        for name in names {
            rng.conv_into(&mut d, name, 3, 3, 3);
        }
        let err = Decoder::<f32>::from_state_dict(&d).expect_err("level 0 refused");
        assert!(matches!(err, NetError::Layout(_)), "{err}");
        assert!(err.to_string().contains(names[0]), "{err}");
        // The encoder's own 1x1 `conv0` present, so the numbering is what is refused.
        rng.conv_into(&mut d, "conv0", 3, 3, 1);
        let err = Encoder::<f32>::from_state_dict(&d).expect_err("level 0 refused");
        assert!(matches!(err, NetError::Layout(_)), "{err}");
    }
}

/// Two tensors of one name cannot be written (the safetensors serializer would otherwise
/// index past its table).
#[test]
fn two_tensors_of_one_name_are_not_serialized() {
    let data = [0u8; 4];
    let view =
        || safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![1], &data).unwrap();
    let err = nets::weights_file::serialize_canonical(
        vec![
            ("a".into(), view()),
            ("b".into(), view()),
            ("a".into(), view()),
        ],
        Default::default(),
    )
    .expect_err("a repeated name is refused");
    assert!(err.contains("`a`"), "{err}");
}

fn expect_err<T: std::fmt::Debug>(r: Result<T, NetError>) -> String {
    r.expect_err("expected an error").to_string()
}

#[test]
fn bad_state_dicts_give_errors_naming_the_tensor() {
    let (vgg, dec) = adain_state_dicts();
    let mut sd = vgg.clone();
    sd.remove("9.bias");
    let msg = expect_err(Encoder::<f32>::from_state_dict(&sd));
    assert!(msg.contains("missing tensor `9.bias`"), "{msg}");

    let mut sd = vgg.clone();
    sd.insert(
        "5.weight".into(),
        TensorF32::new(vec![8, 7, 3, 3], vec![0.0; 504]).unwrap(),
    );
    let msg = expect_err(Encoder::<f32>::from_state_dict(&sd));
    assert!(
        msg.contains("`5.weight`") && msg.contains("[8, 7, 3, 3]"),
        "{msg}"
    );

    let mut sd = vgg.clone();
    sd.insert(
        "2.bias".into(),
        TensorF32::new(vec![9], vec![0.0; 9]).unwrap(),
    );
    let msg = expect_err(Encoder::<f32>::from_state_dict(&sd));
    assert!(msg.contains("`2.bias`"), "{msg}");

    let mut sd = vgg.clone();
    sd.insert(
        "foo.weight".into(),
        TensorF32::new(vec![1], vec![0.0]).unwrap(),
    );
    let msg = expect_err(Encoder::<f32>::from_state_dict(&sd));
    assert!(
        msg.contains("unknown layout") && msg.contains("foo"),
        "{msg}"
    );

    let mut sd = vgg.clone();
    let w = sd.remove("12.weight").unwrap();
    let b = sd.remove("12.bias").unwrap();
    sd.insert("14.weight".into(), w);
    sd.insert("14.bias".into(), b);
    let msg = expect_err(Encoder::<f32>::from_state_dict(&sd));
    assert!(msg.contains("9 and 14"), "{msg}");

    let msg = expect_err(Encoder::<f32>::from_state_dict(&dec));
    assert!(msg.contains("`0.weight`"), "{msg}");
    let msg = expect_err(Decoder::<f32>::from_state_dict(&vgg));
    assert!(msg.contains("index 1"), "{msg}");
    let msg = expect_err(Encoder::<f32>::from_state_dict(&StateDict::new()));
    assert!(msg.contains("empty"), "{msg}");
}

#[test]
fn bad_inputs_give_errors() {
    let (vgg, dec) = adain_state_dicts();
    let enc: Encoder = Encoder::from_state_dict(&vgg)
        .unwrap()
        .with_depth(4)
        .unwrap();
    let dec: Decoder = Decoder::from_state_dict(&dec).unwrap();
    let msg = expect_err(enc.forward(ndarray::Array4::zeros((1, 4, 16, 16)).view()));
    assert!(msg.contains("expects 3 channels, got 4"), "{msg}");
    let msg = expect_err(enc.forward(ndarray::Array4::zeros((1, 3, 1, 16)).view()));
    assert!(msg.contains("2x2"), "{msg}");
    let msg = expect_err(dec.forward(ndarray::Array4::zeros((1, 8, 4, 4)).view()));
    assert!(msg.contains("expects 64 channels"), "{msg}");
    let msg = expect_err(enc.clone().with_depth(5));
    assert!(msg.contains("relu4_1"), "{msg}");
    // A cotangent of the wrong shape.
    let x = ndarray::Array4::<f32>::zeros((1, 3, 16, 16));
    let (_, tape) = enc.forward_with_tape(x.view()).unwrap();
    let bad = ndarray::Array4::<f32>::zeros((1, 8, 15, 16));
    let msg = expect_err(enc.backward(&tape, &[Some(bad.view())]));
    assert!(msg.contains("cotangent 0"), "{msg}");
}

#[test]
fn bad_files_give_errors_naming_the_file() {
    let tmp = TempDir::new("bad_files_give_errors_naming_the_file");
    let path = tmp.path("garbage.safetensors");
    std::fs::write(&path, b"not a safetensors file at all").unwrap();
    let msg = expect_err(NetWeights::load(&path));
    assert!(
        msg.contains("garbage.safetensors") && msg.contains("not a safetensors"),
        "{msg}"
    );

    let missing = tmp.path("does-not-exist.safetensors");
    let msg = expect_err(NetWeights::load(&missing));
    assert!(msg.contains("does-not-exist.safetensors"), "{msg}");

    // A file whose metadata disagrees with its tensors.
    let (vgg, _) = adain_state_dicts();
    let enc: Encoder = Encoder::from_state_dict(&vgg)
        .unwrap()
        .with_depth(2)
        .unwrap();
    let w = NetWeights {
        encoder: Some(enc),
        ..NetWeights::default()
    };
    let sd = w.to_state_dict();
    let mut md = w.metadata();
    md.insert("encoder.widths".into(), "8,17".into());
    let bytes = serialise(&sd, md.clone());
    let path = tmp.path("mismatch.safetensors");
    std::fs::write(&path, bytes).unwrap();
    let msg = expect_err(NetWeights::load(&path));
    assert!(
        msg.contains("mismatch.safetensors") && msg.contains("encoder.widths"),
        "{msg}"
    );

    // A file missing one tensor.
    let mut sd2 = sd.clone();
    sd2.remove("encoder.conv1_2.weight");
    let path = tmp.path("missing-tensor.safetensors");
    std::fs::write(&path, serialise(&sd2, w.metadata())).unwrap();
    let msg = expect_err(NetWeights::load(&path));
    assert!(msg.contains("encoder.conv1_2.weight"), "{msg}");
}

fn serialise(sd: &StateDict, md: std::collections::HashMap<String, String>) -> Vec<u8> {
    let raw: Vec<(String, Vec<usize>, Vec<u8>)> = sd
        .iter()
        .map(|(k, t)| {
            (
                k.clone(),
                t.shape.clone(),
                t.data.iter().flat_map(|v| v.to_le_bytes()).collect(),
            )
        })
        .collect();
    let views: Vec<_> = raw
        .iter()
        .map(|(k, s, b)| {
            (
                k.clone(),
                safetensors::tensor::TensorView::new(safetensors::Dtype::F32, s.clone(), b)
                    .unwrap(),
            )
        })
        .collect();
    safetensors::serialize(views, Some(md)).unwrap()
}

/// A pointwise decoder survives the canonical file as one: its `decoder.kernel` entry, its
/// layers and its outputs; a kernel entry other than 1 or 3 is refused, and a 3x3 decoder's
/// file has no kernel entry (files written before pointwise decoders stay byte-identical).
#[test]
fn pointwise_decoder_round_trips() {
    let tmp = TempDir::new("pointwise_decoder_round_trips");
    let mut rng = TestRng::new(11);
    let widths = [6, 5, 3];
    let layers = (0..2)
        .map(|i| nets::ConvLayer {
            name: format!("conv1_{}", 2 - i),
            source: format!("conv1_{}", 2 - i),
            weight: rng
                .array4((widths[i + 1], widths[i], 1, 1))
                .mapv(|v| v as f32),
            bias: rng.array1(widths[i + 1]).mapv(|v| v as f32),
        })
        .collect();
    let decoder = Decoder::pointwise(layers, false).unwrap();
    let weights = NetWeights {
        decoder: Some(decoder.clone()),
        ..Default::default()
    };
    let path = tmp.path("mlp.safetensors");
    weights.save(&path).unwrap();
    let md = weights.metadata();
    assert_eq!(md["decoder.kernel"], "1");
    assert_eq!(md["decoder.convs_per_level"], "2");
    let back = NetWeights::load(&path).unwrap().decoder.unwrap();
    assert!(back.is_pointwise());
    let x = rng.array4((1, 6, 3, 4)).mapv(|v| v as f32);
    assert_eq!(
        back.forward(x.view()).unwrap(),
        decoder.forward(x.view()).unwrap()
    );
    let (_, dec) = adain_state_dicts();
    let cnn = NetWeights {
        decoder: Some(Decoder::from_state_dict(&dec).unwrap()),
        ..Default::default()
    };
    assert!(!cnn.metadata().contains_key("decoder.kernel"));
    let mut md = weights.metadata();
    md.insert("decoder.kernel".into(), "5".into());
    let bytes = serialise(&weights.to_state_dict(), md);
    let e = NetWeights::from_bytes(&bytes).unwrap_err().to_string();
    assert!(e.contains("decoder.kernel") && e.contains('5'), "{e}");
}
