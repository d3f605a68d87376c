//! The one content hash of the workspace: FNV-1a (64-bit), a cheap identity of inputs and
//! outputs (weights, geometry, bake targets, shard files) recorded beside them and compared when
//! they are read back. It detects accidental change, not tampering.

/// FNV-1a (64-bit) state: feed bytes with [`Fnv1a::eat`], read the hash with [`Fnv1a::hex`].
///
/// ```
/// let mut h = base::Fnv1a::new();
/// h.eat(b"a");
/// // The published FNV-1a 64-bit hash of "a".
/// assert_eq!(h.hex(), "af63dc4c8601ec8c");
/// ```
#[derive(Clone, Copy, Debug)]
pub struct Fnv1a(u64);

impl Default for Fnv1a {
    fn default() -> Self {
        Self::new()
    }
}

impl Fnv1a {
    /// The hash of nothing (the FNV-1a offset basis).
    pub fn new() -> Self {
        Fnv1a(0xcbf2_9ce4_8422_2325)
    }

    /// Feeds `bytes`.
    pub fn eat(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
    }

    /// Feeds the bits of `v`, little-endian.
    pub fn eat_f32(&mut self, v: f32) {
        self.eat(&v.to_bits().to_le_bytes());
    }

    /// Feeds the bits of `v`, little-endian.
    pub fn eat_f64(&mut self, v: f64) {
        self.eat(&v.to_bits().to_le_bytes());
    }

    /// Feeds `v` as 8 little-endian bytes.
    pub fn eat_u64(&mut self, v: u64) {
        self.eat(&v.to_le_bytes());
    }

    /// Feeds a string, preceded by its length (so that `("ab", "c")` and `("a", "bc")` differ).
    pub fn eat_str(&mut self, s: &str) {
        self.eat_u64(s.len() as u64);
        self.eat(s.as_bytes());
    }

    /// The hash as 16 hexadecimal digits.
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

/// The FNV-1a hash of `bytes`, as 16 hexadecimal digits.
pub fn fnv1a_hex(bytes: &[u8]) -> String {
    let mut h = Fnv1a::new();
    h.eat(bytes);
    h.hex()
}
