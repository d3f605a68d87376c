//! Style statistics cache: a style image is encoded once, its per-level channel statistics are
//! kept, and every view (and every training step) reuses them.
//!
//! Entries are keyed by [`StyleKey`]: a tag naming the encoder (its variant and weights, since
//! statistics depend on both) together with either a 64-bit FNV-1a hash of the image's shape and
//! pixel bit patterns (content addressing: the same pixels give the same key wherever they came
//! from) or a file path. The cache is thread-safe; statistics are shared as `Arc`s.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use base::Real;
use ndarray::Array4;

use crate::error::{Result, StyleError};
use crate::stats::{channel_stats, ChannelStats};

/// The statistics of one style image at every encoder level, relu1_1 .. relu_k_1.
#[derive(Clone, Debug, PartialEq)]
pub struct StyleFeatureStats<T> {
    /// Per-channel statistics of each encoder level, shallowest (relu1_1) first; level `l` is
    /// `[N, C_l]` (usually `N = 1`, broadcast over a batch).
    pub levels: Vec<ChannelStats<T>>,
}

impl<T: Real> StyleFeatureStats<T> {
    /// Statistics of every level of an encoded style image.
    pub fn from_features(features: &[Array4<T>]) -> Result<Self> {
        if features.is_empty() {
            return Err(StyleError::Invalid {
                what: "style statistics",
                problem: "no feature levels given".into(),
            });
        }
        Ok(StyleFeatureStats {
            levels: features.iter().map(channel_stats).collect::<Result<_>>()?,
        })
    }

    /// The deepest level (relu_k_1): the statistics that AdaIN and the 3D transform use.
    pub fn deepest(&self) -> &ChannelStats<T> {
        self.levels
            .last()
            .expect("at least one level by construction")
    }
}

/// What identifies a style image in a [`StyleCache`].
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct StyleKey {
    encoder: String,
    source: KeySource,
}

#[derive(Clone, Debug, PartialEq, Eq, Hash)]
enum KeySource {
    Content { shape: [usize; 4], hash: u64 },
    Path(PathBuf),
}

/// 64-bit FNV-1a.
fn fnv1a(bytes: impl Iterator<Item = u8>, mut h: u64) -> u64 {
    for b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

impl StyleKey {
    /// A key from the image's pixels (`[N, 3, H, W]`, any layout) and an encoder tag. Pixels are
    /// hashed as the bit patterns of their exact `f64` values, so an `f32` image and its `f64`
    /// copy share a key.
    pub fn from_image<T: Real>(encoder: &str, image: &Array4<T>) -> StyleKey {
        let d = image.dim();
        let shape = [d.0, d.1, d.2, d.3];
        let h = fnv1a(
            shape.iter().flat_map(|s| (*s as u64).to_le_bytes()),
            0xcbf2_9ce4_8422_2325,
        );
        let hash = fnv1a(
            image
                .iter()
                .flat_map(|v| v.to_f64_exact().to_bits().to_le_bytes()),
            h,
        );
        StyleKey {
            encoder: encoder.to_string(),
            source: KeySource::Content { shape, hash },
        }
    }

    /// A key from the style image's file path and an encoder tag (the caller vouches that the
    /// file does not change while the cache lives).
    pub fn from_path(encoder: &str, path: &Path) -> StyleKey {
        StyleKey {
            encoder: encoder.to_string(),
            source: KeySource::Path(path.to_path_buf()),
        }
    }
}

/// A thread-safe map from style keys to their statistics, with hit and miss counts.
#[derive(Debug, Default)]
pub struct StyleCache<T> {
    inner: Mutex<CacheInner<T>>,
}

#[derive(Debug)]
struct CacheInner<T> {
    map: HashMap<StyleKey, Arc<StyleFeatureStats<T>>>,
    hits: u64,
    misses: u64,
}

impl<T> Default for CacheInner<T> {
    fn default() -> Self {
        CacheInner {
            map: HashMap::new(),
            hits: 0,
            misses: 0,
        }
    }
}

impl<T: Real> StyleCache<T> {
    /// An empty cache.
    pub fn new() -> Self {
        StyleCache {
            inner: Mutex::new(CacheInner::default()),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, CacheInner<T>> {
        // A panic while holding the lock cannot leave the map half-updated (every update is a
        // single insert), so a poisoned lock is still usable.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The statistics for `key`, computing them with `compute` on the first request. The lock is
    /// not held while computing; if two threads race on one key, the first result is kept.
    pub fn get_or_compute(
        &self,
        key: &StyleKey,
        compute: impl FnOnce() -> Result<StyleFeatureStats<T>>,
    ) -> Result<Arc<StyleFeatureStats<T>>> {
        {
            let mut inner = self.lock();
            if let Some(found) = inner.map.get(key).cloned() {
                inner.hits += 1;
                return Ok(found);
            }
        }
        let fresh = Arc::new(compute()?);
        let mut inner = self.lock();
        inner.misses += 1;
        Ok(inner.map.entry(key.clone()).or_insert(fresh).clone())
    }

    /// The cached statistics for `key`, if present.
    pub fn get(&self, key: &StyleKey) -> Option<Arc<StyleFeatureStats<T>>> {
        self.lock().map.get(key).cloned()
    }

    /// Number of cached styles.
    pub fn len(&self) -> usize {
        self.lock().map.len()
    }

    /// Whether the cache is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `(hits, misses)` so far.
    pub fn counts(&self) -> (u64, u64) {
        let inner = self.lock();
        (inner.hits, inner.misses)
    }
}
