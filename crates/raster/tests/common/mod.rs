//! Shared test support: oracle fixture cases and a dense reference rasterizer.
#![allow(dead_code)]

use dsgs_testkit::Fixture;
use gaussian::Real;
use raster::{rasterize, rasterize_backward, Cotangents, Rasterized, SplatGrads, Splats};

/// The five cases of `oracle/fixtures/raster.safetensors`.
pub const CASES: [&str; 5] = ["basic", "features", "saturated", "edges", "sh3"];

pub fn raster_fixture() -> Fixture {
    Fixture::shared("oracle/fixtures/raster.safetensors")
}

/// One oracle case at the rasterizer level: projected inputs, cotangents and expected values.
pub struct RasterCase {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub channel_count: usize,
    pub means2d: Vec<[f64; 2]>,
    pub conics: Vec<[f64; 3]>,
    pub depths: Vec<f64>,
    pub radii: Vec<[u32; 2]>,
    pub opacity_logits: Vec<f64>,
    pub channels: Vec<f64>,
    pub background: Vec<f64>,
    pub v_image: Vec<f64>,
    pub v_alpha: Vec<f64>,
    pub v_depth: Vec<f64>,
}

pub fn rows<const K: usize>(data: &[f64]) -> Vec<[f64; K]> {
    data.chunks_exact(K)
        .map(|c| std::array::from_fn(|i| c[i]))
        .collect()
}

pub fn cast<T: Real>(v: &[f64]) -> Vec<T> {
    v.iter().map(|&x| T::lit(x)).collect()
}

pub fn cast_rows<T: Real, const K: usize>(v: &[[f64; K]]) -> Vec<[T; K]> {
    v.iter().map(|r| r.map(T::lit)).collect()
}

pub fn to_f64<T: Real>(v: &[T]) -> Vec<f64> {
    v.iter().map(|x| x.to_f64_exact()).collect()
}

pub fn flat<T: Real, const K: usize>(v: &[[T; K]]) -> Vec<f64> {
    v.iter().flatten().map(|x| x.to_f64_exact()).collect()
}

pub fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

impl RasterCase {
    pub fn load(f: &Fixture, name: &str) -> RasterCase {
        let g = |k: &str| f.get(&format!("{name}.{k}"));
        let size = &g("size_wh").data;
        let (width, height) = (size[0] as u32, size[1] as u32);
        let channels = if f.has(&format!("{name}.colors")) {
            g("colors")
        } else {
            g("features")
        };
        let channel_count = *channels.shape.last().unwrap();
        RasterCase {
            name: name.to_string(),
            width,
            height,
            channel_count,
            means2d: rows(&g("means2d").data),
            conics: rows(&g("conics").data),
            depths: g("depths").data.clone(),
            radii: rows::<2>(&g("radii").data)
                .iter()
                .map(|r| [r[0] as u32, r[1] as u32])
                .collect(),
            opacity_logits: g("opacity_logits").data.clone(),
            channels: channels.data.clone(),
            background: g("background").data.clone(),
            v_image: g("v_image").data.clone(),
            v_alpha: g("v_alpha").data.clone(),
            v_depth: g("v_depth").data.clone(),
        }
    }

    pub fn opacities(&self) -> Vec<f64> {
        self.opacity_logits.iter().map(|&x| sigmoid(x)).collect()
    }

    /// Runs forward and backward in precision `T` (inputs rounded to `T`).
    pub fn run<T: Real>(&self) -> (Rasterized<T>, SplatGrads<T>) {
        let means2d = cast_rows::<T, 2>(&self.means2d);
        let conics = cast_rows::<T, 3>(&self.conics);
        let depths = cast::<T>(&self.depths);
        let opacities = cast::<T>(&self.opacities());
        let channels = cast::<T>(&self.channels);
        let background = cast::<T>(&self.background);
        let splats = Splats {
            means2d: &means2d,
            conics: &conics,
            depths: &depths,
            radii: &self.radii,
            opacities: &opacities,
            channels: &channels,
            channel_count: self.channel_count,
        };
        let out = rasterize(&splats, self.width, self.height, &background).unwrap();
        let v_image = cast::<T>(&self.v_image);
        let v_alpha = cast::<T>(&self.v_alpha);
        let v_depth = cast::<T>(&self.v_depth);
        let cot = Cotangents {
            image: &v_image,
            alpha: Some(&v_alpha),
            depth: Some(&v_depth),
        };
        let grads = rasterize_backward(&splats, &out.bins, &background, &cot).unwrap();
        (out, grads)
    }
}

/// Gradient of the loss with respect to the opacity logits, from the gradient with respect to
/// the opacities: `dL/dx = dL/do sigmoid'(x)`.
pub fn logit_grads<T: Real>(v_opacities: &[T], logits: &[f64]) -> Vec<f64> {
    v_opacities
        .iter()
        .zip(logits)
        .map(|(&g, &x)| {
            let o = sigmoid(x);
            g.to_f64_exact() * o * (1.0 - o)
        })
        .collect()
}
