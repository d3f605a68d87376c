//! Test support shared by the dsgs crates (a dev-dependency only).
//!
//! * [`shared_dir`] locates the read-only reference material: the `DSGS_SHARED` environment
//!   variable if set, otherwise `../shared` beside the workspace root. [`repo_fixture`] names a
//!   small input kept in the repository's `fixtures/`; [`scratch_dir`] makes a fresh temporary
//!   directory.
//! * [`Fixture`] reads an oracle safetensors file and hands out tensors as `f64`, whatever their
//!   stored dtype (the oracle stores float64; the real-weights file stores float32).
//!   [`oracle`] names the oracle's files and cases; [`arrays`] turns tensors into `ndarray`
//!   arrays in either precision.
//! * [`max_rel_err`] and [`assert_close`] compare results with a reference using one definition of
//!   relative error for the whole project: the largest absolute difference divided by the largest
//!   reference magnitude (an infinity-norm relative error). Element-wise relative error is
//!   meaningless for entries that are zero in the reference, which gradients routinely have.
//! * [`SplitMix64`] generates deterministic test values.
//!
//! Dependencies: a crate whose own tests use the testkit must not be a dependency of it (that
//! would be a dependency cycle), so the helpers are generic over [`base::Real`], `ndarray` arrays
//! and plain slices. What needs a workspace crate's types is either a macro expanded in the caller
//! ([`oracle_camera!`], for `gaussian`) or, for the crates downstream of `nets` (style, train),
//! the module `nets` behind the cargo feature of the same name, which the tests of `nets` itself
//! do not enable.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use base::Real;
use safetensors::{Dtype, SafeTensors};

pub mod arrays;
pub mod fuzz;
#[cfg(feature = "nets")]
pub mod nets;
pub mod oracle;
mod rng;

pub use rng::SplitMix64;

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

/// A file of the repository's `fixtures/` directory (small test inputs kept with the code).
pub fn repo_fixture(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures")
        .join(rel)
}

/// A fresh, empty scratch directory `dsgs-{tag}-{process id}-{name}` in the system's temporary
/// directory (whatever an earlier run left there is removed first).
pub fn scratch_dir(tag: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("dsgs-{tag}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
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

    /// The rows of a tensor whose last dimension is `K`, as arrays (asserting that dimension).
    pub fn rows<const K: usize>(&self, name: &str) -> Vec<[f64; K]> {
        let t = self.get(name);
        assert_eq!(
            t.shape.last().copied(),
            Some(K),
            "{name} has shape {:?}",
            t.shape
        );
        t.data
            .chunks_exact(K)
            .map(|c| std::array::from_fn(|i| c[i]))
            .collect()
    }

    /// The tensors named `{prefix}*`, prefix removed, rounded to `f32` and built by
    /// `new(shape, data)` (`None` for a shape that does not fit the data), e.g.
    /// `fx.f32_tensors("vgg.", nets::TensorF32::new)` for a state dict of `nets`.
    pub fn f32_tensors<V, C>(
        &self,
        prefix: &str,
        new: impl Fn(Vec<usize>, Vec<f32>) -> Option<V>,
    ) -> C
    where
        C: FromIterator<(String, V)>,
    {
        self.names()
            .into_iter()
            .filter_map(|n| {
                n.strip_prefix(prefix).map(|k| {
                    let t = self.get(n);
                    let v = new(t.shape.clone(), t.to_f32()).expect("shape");
                    (k.to_string(), v)
                })
            })
            .collect()
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
#[track_caller]
pub fn assert_close(what: &str, actual: &[f64], expected: &[f64], tol: f64) {
    assert_within(what, max_rel_err(actual, expected), tol);
}

/// [`assert_close`] that first prints the error to stderr (`cargo test -- --nocapture` shows the
/// figures).
#[track_caller]
pub fn assert_close_verbose(what: &str, actual: &[f64], expected: &[f64], tol: f64) {
    let err = max_rel_err(actual, expected);
    eprintln!("{what}: max relative error {err:.2e}");
    assert_within(what, err, tol);
}

#[track_caller]
fn assert_within(what: &str, err: f64, tol: f64) {
    assert!(
        err <= tol,
        "{what}: max relative error {err:.3e} exceeds {tol:.1e}"
    );
}

/// [`assert_close`] for `f32` results.
#[track_caller]
pub fn assert_close_f32(what: &str, actual: &[f32], expected: &[f64], tol: f64) {
    assert_close(what, &to_f64(actual), expected, tol);
}

/// Values as `f64` (exactly), in iteration order: slices, vectors and `ndarray` arrays alike.
pub fn to_f64<'a, T: Real>(values: impl IntoIterator<Item = &'a T>) -> Vec<f64> {
    values.into_iter().map(|x| x.to_f64_exact()).collect()
}

/// Rows of `K` values as one `f64` vector, row-major.
pub fn flat<T: Real, const K: usize>(rows: &[[T; K]]) -> Vec<f64> {
    rows.iter().flatten().map(|x| x.to_f64_exact()).collect()
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
    fn splitmix64_matches_the_reference_sequence() {
        // Pins the sequence: the random test values of every crate derive from it.
        let mut r = SplitMix64(1234567);
        assert_eq!(r.next_u64(), 6457827717110365317);
        assert_eq!(r.next_u64(), 3203168211198807973);
        let u = r.uniform(-2.0, 3.0);
        assert!((-2.0..3.0).contains(&u));
    }

    #[test]
    fn oracle_fixtures_open() {
        let f = Fixture::shared("oracle/fixtures/raster.safetensors");
        let k = f.get("basic.K");
        assert_eq!(k.shape, vec![3, 3]);
        // The fixture convention (the docstring of gen_fixtures.py): K = [[fx, 0, cx], [0, fy,
        // cy], [0, 0, 1]] with positive focal lengths, whatever the seed and size.
        let d = &k.data;
        assert!(d.iter().all(|v| v.is_finite()), "K has a non-finite entry");
        assert!(
            d[0] > 0.0 && d[4] > 0.0,
            "K has a non-positive focal length"
        );
        assert_eq!([d[1], d[3], d[6], d[7], d[8]], [0.0, 0.0, 0.0, 0.0, 1.0]);
        // The image size the camera belongs to has two positive entries.
        let wh = f.get("basic.size_wh");
        assert_eq!(wh.shape, vec![2]);
        assert!(wh.data.iter().all(|&v| v >= 1.0));
    }
}
