//! The built-in decoder and the named network pairs: the shipped file holds a decoder and
//! nothing of the shared folder (no encoder), pairs with the compressed relu4_1 encoder it was
//! trained for, and stylizes through it: the AdaIN output of a photograph and a painting,
//! decoded and measured by the loss network it was trained with, has channel statistics closer
//! to the painting's than the photograph has.

use dsgs_testkit::shared_path;
use nets::{Encoder, NetWeights};
use pipeline::image_io::{load_style_image, nchw_from_rgb};
use pipeline::weights::{built_in_decoder, Pair, BUILT_IN_DECODER};
use style::adain::adain;
use style::loss::style_loss;
use style::stats::channel_stats;

#[test]
fn the_built_in_file_holds_a_decoder_only() {
    let w = NetWeights::from_bytes(BUILT_IN_DECODER).unwrap();
    assert!(w.decoder.is_some());
    // The encoder is read from the shared folder, never shipped.
    assert!(w.encoder.is_none() && w.lifter.is_none());
}

#[test]
fn the_relu4_1_pair_fits_together() {
    let encoder: Encoder<f32> =
        Encoder::from_checkpoint(&shared_path(Pair::Relu41.encoder())).unwrap();
    let decoder = built_in_decoder().unwrap();
    assert_eq!(Pair::Relu41.decoder(), None);
    assert_eq!(decoder.in_channels(), *encoder.widths().last().unwrap());
    assert_eq!(decoder.depth(), encoder.depth());

    // Measured by the loss network the decoder was trained with (the real VGG-19 to relu3_1,
    // card: `crates/pipeline/weights/relu41-decoder.md`), as its training measured it.
    let vgg: Encoder<f32> = Encoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
    ))
    .unwrap();
    let image = |name: &str| {
        nchw_from_rgb(&load_style_image(&shared_path(&format!("data/{name}")), 128).unwrap())
    };
    let photo = image("content/chicago.jpg");
    let photo_code = encoder.forward(photo.view()).unwrap();
    for painting in ["styles/mondrian.jpg", "styles/woman_with_hat_matisse.jpg"] {
        let painting = image(painting);
        let code = encoder.forward(painting.view()).unwrap();
        let t = adain(photo_code.last().unwrap(), code.last().unwrap()).unwrap();
        let out = decoder.forward(t.view()).unwrap();
        let target: Vec<_> = vgg
            .forward(painting.view())
            .unwrap()
            .iter()
            .map(|l| channel_stats(l).unwrap())
            .collect();
        let stylized = style_loss(&vgg.forward(out.view()).unwrap(), &target).unwrap();
        let before = style_loss(&vgg.forward(photo.view()).unwrap(), &target).unwrap();
        assert!(stylized < before, "{stylized} vs the photo's {before}");
    }
}

#[test]
fn pair_names_round_trip() {
    for name in Pair::NAMES {
        let p: Pair = name.parse().unwrap();
        assert_eq!(p.as_str(), *name);
    }
    let err = "relu5_1".parse::<Pair>().unwrap_err();
    assert!(err.contains("relu4_1, wct-relu3_1"), "{err}");
}
