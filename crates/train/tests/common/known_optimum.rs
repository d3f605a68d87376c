//! Networks with a known optimum, for training tests whose claims must hold for any weights, not
//! for one set of random weights: [`InvertibleNets`] is an encoder and the decoder that inverts it
//! exactly, built from a seed.
//!
//! Every encoder convolution uses only its centre tap, with a matrix of positive entries around
//! the identity and positive biases; on a positive input every ReLU therefore passes its input,
//! and the fullres encoder (no pooling) is an affine map per pixel with positive values
//! throughout. Each decoder conv is the left inverse of the encoder conv it mirrors (the last one
//! also undoes the 1x1 input conv), so `decoder(encoder(x)) = x` for every positive image `x`
//! (up to rounding), and the decoder's intermediate values are the encoder's, positive too.

#![allow(dead_code)]

use gaussian::dataset::images::RgbImage;
use nets::{Decoder, Encoder, StateDict, TensorF32};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

/// A matrix, rows of columns.
type Mat = Vec<Vec<f64>>;

fn mat_mul(a: &Mat, b: &Mat) -> Mat {
    a.iter()
        .map(|row| {
            (0..b[0].len())
                .map(|j| row.iter().zip(b).map(|(x, brow)| x * brow[j]).sum())
                .collect()
        })
        .collect()
}

fn mat_vec(a: &Mat, x: &[f64]) -> Vec<f64> {
    a.iter()
        .map(|row| row.iter().zip(x).map(|(p, q)| p * q).sum())
        .collect()
}

fn transpose(a: &Mat) -> Mat {
    (0..a[0].len())
        .map(|j| a.iter().map(|row| row[j]).collect())
        .collect()
}

/// The inverse of a square matrix (Gauss-Jordan with partial pivoting).
fn inverse(a: &Mat) -> Mat {
    let n = a.len();
    let mut m: Mat = a
        .iter()
        .enumerate()
        .map(|(i, row)| {
            let mut r = row.clone();
            r.extend((0..n).map(|j| if i == j { 1.0 } else { 0.0 }));
            r
        })
        .collect();
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&p, &q| m[p][col].abs().total_cmp(&m[q][col].abs()))
            .expect("non-empty");
        m.swap(col, pivot);
        let d = m[col][col];
        assert!(d.abs() > 1e-9, "singular matrix");
        for v in m[col].iter_mut() {
            *v /= d;
        }
        for r in 0..n {
            if r != col {
                let f = m[r][col];
                let pivot_row = m[col].clone();
                for (v, p) in m[r].iter_mut().zip(&pivot_row) {
                    *v -= f * p;
                }
            }
        }
    }
    m.into_iter().map(|row| row[n..].to_vec()).collect()
}

/// A per-pixel affine map `x -> m x + b`.
#[derive(Clone, Debug)]
struct Affine {
    m: Mat,
    b: Vec<f64>,
}

impl Affine {
    fn apply(&self, x: &[f64]) -> Vec<f64> {
        mat_vec(&self.m, x)
            .into_iter()
            .zip(&self.b)
            .map(|(v, b)| v + b)
            .collect()
    }

    /// `next` after `self`.
    fn then(&self, next: &Affine) -> Affine {
        Affine {
            m: mat_mul(&next.m, &self.m),
            b: next.apply(&self.b),
        }
    }

    /// The left inverse `y -> L (y - b)` with `L = (m^T m)^-1 m^T` (`m` has full column rank).
    fn left_inverse(&self) -> Affine {
        let mt = transpose(&self.m);
        let l = mat_mul(&inverse(&mat_mul(&mt, &self.m)), &mt);
        let b = mat_vec(&l, &self.b).into_iter().map(|v| -v).collect();
        Affine { m: l, b }
    }

    /// A map from `inputs` to `outputs >= inputs` channels: entry `(i, j)` is 1 when
    /// `i mod inputs = j`, plus a uniform draw in `[0, 0.1)`; biases in `[0.01, 0.05)`.
    fn positive_near_identity(outputs: usize, inputs: usize, rng: &mut StdRng) -> Affine {
        let m = (0..outputs)
            .map(|i| {
                (0..inputs)
                    .map(|j| f64::from(u8::from(i % inputs == j)) + rng.random_range(0.0..0.1))
                    .collect()
            })
            .collect();
        let b = (0..outputs).map(|_| rng.random_range(0.01..0.05)).collect();
        Affine { m, b }
    }

    fn tensors(&self, kernel: usize) -> (TensorF32, TensorF32) {
        let (o, c) = (self.m.len(), self.m[0].len());
        let taps = kernel * kernel;
        let mut w = vec![0.0f32; o * c * taps];
        for (i, row) in self.m.iter().enumerate() {
            for (j, &v) in row.iter().enumerate() {
                w[(i * c + j) * taps + taps / 2] = v as f32;
            }
        }
        let b = self.b.iter().map(|&v| v as f32).collect();
        (
            TensorF32::new(vec![o, c, kernel, kernel], w).expect("weight shape"),
            TensorF32::new(vec![o], b).expect("bias shape"),
        )
    }
}

/// An encoder and the decoder that inverts it exactly on positive images (module documentation).
pub struct InvertibleNets {
    /// The encoder (standard resolution as built; training sets the variant's).
    pub encoder: Encoder<f32>,
    /// Its inverse.
    pub decoder: Decoder<f32>,
    /// The 1x1 input conv, then the 3x3 convs in execution order, as affine maps.
    maps: Vec<Affine>,
}

impl InvertibleNets {
    /// Networks from `seed`, to `relu{depth}_1` with `depth = widths.len()`: level `k` (from 1)
    /// has `convs_per_level[k-1]` convs of width `widths[k-1]` (the deepest level runs only its
    /// first). Widths must not decrease and start at 3 or more, so that each conv has a left
    /// inverse.
    pub fn new(seed: u64, widths: &[usize], convs_per_level: &[usize]) -> InvertibleNets {
        assert_eq!(widths.len(), convs_per_level.len());
        let mut rng = StdRng::seed_from_u64(seed);
        let mut maps = vec![Affine::positive_near_identity(3, 3, &mut rng)];
        // nn.Sequential indices: the 1x1 conv at 0, the first 3x3 conv at 2, then 3 apart
        // within a level and 4 apart across a pool (the decoder: 1, then 3 and 4 apart).
        let mut enc = StateDict::new();
        let (w, b) = maps[0].tensors(1);
        enc.insert("0.weight".into(), w);
        enc.insert("0.bias".into(), b);
        let mut index = 2;
        let mut width = 3;
        // The convs the encoder runs: every conv of a level, but only the first of the last.
        let runs: Vec<usize> = convs_per_level
            .iter()
            .enumerate()
            .map(|(k, &n)| if k + 1 == widths.len() { 1 } else { n })
            .collect();
        for (k, (&out, &n)) in widths.iter().zip(&runs).enumerate() {
            assert!(out >= width, "widths must not decrease");
            if k > 0 {
                index += 1;
            }
            for _ in 0..n {
                let a = Affine::positive_near_identity(out, width, &mut rng);
                let (w, b) = a.tensors(3);
                enc.insert(format!("{index}.weight"), w);
                enc.insert(format!("{index}.bias"), b);
                maps.push(a);
                width = out;
                index += 3;
            }
        }
        let encoder = Encoder::from_state_dict(&enc).expect("encoder");

        // The decoder mirrors the encoder's convs: `levels[k]` = their indices in `maps`.
        let mut levels: Vec<Vec<usize>> = Vec::new();
        let mut l = 1;
        for &n in &runs {
            levels.push((l..l + n).collect());
            l += n;
        }
        let mut dec = StateDict::new();
        let mut index = 1;
        for (g, level) in levels.iter().rev().enumerate() {
            if g > 0 {
                index += 1;
            }
            for &l in level.iter().rev() {
                // decoder conv1_1 also undoes the input conv
                let forward = if l == 1 {
                    maps[0].then(&maps[1])
                } else {
                    maps[l].clone()
                };
                let (w, b) = forward.left_inverse().tensors(3);
                dec.insert(format!("{index}.weight"), w);
                dec.insert(format!("{index}.bias"), b);
                index += 3;
            }
        }
        let decoder = Decoder::from_state_dict(&dec).expect("decoder");
        InvertibleNets {
            encoder,
            decoder,
            maps,
        }
    }

    /// The pixel whose deepest encoder features are `y`, when every conv is square (all widths
    /// 3) and every activation on the way is at least `margin`; `None` otherwise.
    pub fn preimage(&self, y: &[f64], margin: f64) -> Option<[f64; 3]> {
        let whole = self.maps[1..]
            .iter()
            .fold(self.maps[0].clone(), |acc, m| acc.then(m));
        assert_eq!(whole.m.len(), 3, "the encoder must end with 3 channels");
        let x = whole.left_inverse().apply(y);
        let mut v = x.clone();
        if v.iter().any(|&c| c < margin) {
            return None;
        }
        for m in &self.maps {
            v = m.apply(&v);
            if v.iter().any(|&c| c < margin) {
                return None;
            }
        }
        Some([x[0], x[1], x[2]])
    }
}

/// A `side x side` image of independent uniform values in `[0.25, 0.75)`.
pub fn positive_image(seed: u64, side: u32) -> RgbImage {
    let mut rng = StdRng::seed_from_u64(seed);
    RgbImage {
        width: side,
        height: side,
        data: (0..side * side * 3)
            .map(|_| rng.random_range(0.25f32..0.75))
            .collect(),
    }
}

/// Adds independent `N(0, sigma^2)` noise to every weight and bias of `layers`.
pub fn perturb<'a>(
    layers: impl Iterator<Item = &'a mut nets::ConvLayer<f32>>,
    seed: u64,
    sigma: f64,
) {
    let mut rng = StdRng::seed_from_u64(seed);
    for l in layers {
        for v in l.weight.iter_mut().chain(l.bias.iter_mut()) {
            *v += (sigma * rng.sample::<f64, _>(StandardNormal)) as f32;
        }
    }
}
