//! Test support shared by the dsgs crates (a dev-dependency only).
//!
//! * [`shared_dir`] locates the read-only reference material: the `DSGS_SHARED` environment
//!   variable if set, otherwise `../shared` beside the workspace root.
//! * [`Fixture`] reads an oracle safetensors file and hands out tensors as `f64`, whatever their
//!   stored dtype (the oracle stores float64; the real-weights file stores float32).
//! * [`max_rel_err`] and [`assert_close`] compare results with a reference using one definition of
//!   relative error for the whole project: the largest absolute difference divided by the largest
//!   reference magnitude (an infinity-norm relative error). Element-wise relative error is
//!   meaningless for entries that are zero in the reference, which gradients routinely have.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};

/// The environment variable that points at the shared reference material.
pub const SHARED_ENV: &str = "DSGS_SHARED";

/// The shared reference directory. Panics with a clear message when it cannot be found, because a
/// test that needs it cannot say anything without it.
pub fn shared_dir() -> PathBuf {
    let dir = match std::env::var_os(SHARED_ENV) {
        Some(d) => PathBuf::from(d),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
    };
    assert!(
        dir.is_dir(),
        "shared reference data not found at {} (set {SHARED_ENV} to its location)",
        dir.display()
    );
    dir
}

/// A path inside the shared reference directory, e.g. `shared_path("oracle/fixtures/raster.safetensors")`.
pub fn shared_path(rel: &str) -> PathBuf {
    shared_dir().join(rel)
}

/// A tensor read from a fixture, converted to `f64`, row-major.
#[derive(Clone, Debug)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl Tensor {
    /// The data as `f32`.
    pub fn to_f32(&self) -> Vec<f32> {
        self.data.iter().map(|&v| v as f32).collect()
    }

    /// The single value of a scalar (or one-element) tensor.
    pub fn scalar(&self) -> f64 {
        assert_eq!(
            self.data.len(),
            1,
            "tensor of shape {:?} is not a scalar",
            self.shape
        );
        self.data[0]
    }
}

/// All tensors of one safetensors file, decoded eagerly.
pub struct Fixture {
    path: PathBuf,
    tensors: HashMap<String, Tensor>,
}

impl Fixture {
    /// Opens a fixture by path relative to the shared directory.
    pub fn shared(rel: &str) -> Fixture {
        Fixture::open(&shared_path(rel))
    }

    /// Opens a safetensors file anywhere.
    pub fn open(path: &Path) -> Fixture {
        let bytes = std::fs::read(path)
            .unwrap_or_else(|e| panic!("cannot read fixture {}: {e}", path.display()));
        let st = SafeTensors::deserialize(&bytes)
            .unwrap_or_else(|e| panic!("{} is not a safetensors file: {e}", path.display()));
        let mut tensors = HashMap::new();
        for (name, view) in st.tensors() {
            let raw = view.data();
            let data: Vec<f64> = match view.dtype() {
                Dtype::F64 => raw
                    .chunks_exact(8)
                    .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                    .collect(),
                Dtype::F32 => raw
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
                    .collect(),
                Dtype::I64 => raw
                    .chunks_exact(8)
                    .map(|c| i64::from_le_bytes(c.try_into().unwrap()) as f64)
                    .collect(),
                Dtype::I32 => raw
                    .chunks_exact(4)
                    .map(|c| i32::from_le_bytes(c.try_into().unwrap()) as f64)
                    .collect(),
                other => panic!(
                    "{}: tensor {name} has unsupported dtype {other:?}",
                    path.display()
                ),
            };
            tensors.insert(
                name.to_string(),
                Tensor {
                    shape: view.shape().to_vec(),
                    data,
                },
            );
        }
        Fixture {
            path: path.to_path_buf(),
            tensors,
        }
    }

    /// A tensor by name; panics naming the file and the key when it is absent.
    pub fn get(&self, name: &str) -> &Tensor {
        self.tensors
            .get(name)
            .unwrap_or_else(|| panic!("{} has no tensor named {name}", self.path.display()))
    }

    /// Whether a tensor is present.
    pub fn has(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }

    /// All tensor names, sorted.
    pub fn names(&self) -> Vec<&str> {
        let mut v: Vec<&str> = self.tensors.keys().map(String::as_str).collect();
        v.sort_unstable();
        v
    }
}

/// Infinity-norm relative error: `max |a - e| / max |e|` (or the absolute error when the reference
/// is identically zero). Panics if the lengths differ or a value is not finite.
pub fn max_rel_err(actual: &[f64], expected: &[f64]) -> f64 {
    assert_eq!(actual.len(), expected.len(), "length mismatch");
    let mut diff = 0.0f64;
    let mut scale = 0.0f64;
    for (&a, &e) in actual.iter().zip(expected) {
        assert!(a.is_finite(), "non-finite value {a} in the result");
        diff = diff.max((a - e).abs());
        scale = scale.max(e.abs());
    }
    if scale == 0.0 {
        diff
    } else {
        diff / scale
    }
}

/// Asserts `max_rel_err(actual, expected) <= tol`, naming the quantity on failure.
pub fn assert_close(what: &str, actual: &[f64], expected: &[f64], tol: f64) {
    let err = max_rel_err(actual, expected);
    assert!(
        err <= tol,
        "{what}: max relative error {err:.3e} exceeds {tol:.1e}"
    );
}

/// [`assert_close`] for `f32` results.
pub fn assert_close_f32(what: &str, actual: &[f32], expected: &[f64], tol: f64) {
    let a: Vec<f64> = actual.iter().map(|&v| v as f64).collect();
    assert_close(what, &a, expected, tol);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_error_is_scaled_by_the_reference_magnitude() {
        assert_eq!(max_rel_err(&[1.0, 2.0], &[1.0, 2.0]), 0.0);
        assert!((max_rel_err(&[1.0, 2.1], &[1.0, 2.0]) - 0.05).abs() < 1e-12);
        assert!((max_rel_err(&[0.5], &[0.0]) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn oracle_fixtures_open() {
        let f = Fixture::shared("oracle/fixtures/raster.safetensors");
        let k = f.get("basic.K");
        assert_eq!(k.shape, vec![3, 3]);
        assert_eq!(k.data[0], 40.0);
    }
}
