//! Tests of the PyTorch checkpoint importer.
//!
//! * The fixture checkpoints (both file formats) equal `checkpoints.safetensors` bit for bit.
//! * The real pretrained weights import with the keys, shapes and value fingerprints that
//!   PyTorch reports for them (`torch.load`, recorded in `REAL_WEIGHTS`).
//! * Hand-built checkpoints cover what the fixtures do not: float16/bfloat16/float64 storages,
//!   strided views, legacy storage views, pickle protocol 4 opcodes, wrappers, nesting, byte order.
//! * Hostile input (malicious globals and opcodes, absurd sizes, truncations, flipped bytes)
//!   gives an error, never a panic, and never runs or allocates anything unbounded.

use std::collections::BTreeMap;
use std::path::PathBuf;

use dsgs_testkit::{shared_path, Fixture};
use nets::checkpoint::{load_checkpoint, load_checkpoint_bytes, CheckpointError, FormatError};
use nets::{StateDict, TensorF32};

// ---------------------------------------------------------------------------------------------
// Builders for hand-made checkpoints. They follow the byte layouts of `pickle` (protocol 2/4),
// PyTorch's legacy format and the zip APPNOTE independently of the importer.
// ---------------------------------------------------------------------------------------------

/// Emits pickle opcodes.
#[derive(Default)]
struct Pickler(Vec<u8>);

impl Pickler {
    fn new(protocol: u8) -> Pickler {
        Pickler(vec![0x80, protocol])
    }
    fn op(&mut self, b: u8) -> &mut Self {
        self.0.push(b);
        self
    }
    fn raw(&mut self, b: &[u8]) -> &mut Self {
        self.0.extend_from_slice(b);
        self
    }
    fn global(&mut self, module: &str, name: &str) -> &mut Self {
        self.op(b'c').raw(module.as_bytes()).op(b'\n');
        self.raw(name.as_bytes()).op(b'\n')
    }
    fn str(&mut self, s: &str) -> &mut Self {
        self.op(b'X')
            .raw(&(s.len() as u32).to_le_bytes())
            .raw(s.as_bytes())
    }
    fn int(&mut self, i: i64) -> &mut Self {
        match i32::try_from(i) {
            Ok(v) => self.op(b'J').raw(&v.to_le_bytes()),
            Err(_) => self.op(0x8a).op(8).raw(&i.to_le_bytes()),
        }
    }
    fn ints(&mut self, v: &[i64]) -> &mut Self {
        self.op(b'(');
        for &i in v {
            self.int(i);
        }
        self.op(b't')
    }
    /// `_rebuild_tensor_v2(persistent storage, offset, size, stride, False, OrderedDict())`.
    fn tensor(&mut self, s: &StorageSpec, offset: i64, size: &[i64], stride: &[i64]) -> &mut Self {
        self.global("torch._utils", "_rebuild_tensor_v2").op(b'(');
        self.op(b'(')
            .str("storage")
            .global("torch", s.class)
            .str(s.key)
            .str("cpu");
        self.int(s.numel);
        match s.view {
            None if s.legacy => self.op(b'N'),
            None => self,
            Some((key, off, len)) => self.op(b'(').str(key).int(off).int(len).op(b't'),
        };
        self.op(b't')
            .op(b'Q')
            .int(offset)
            .ints(size)
            .ints(stride)
            .op(0x89);
        self.global("collections", "OrderedDict").op(b')').op(b'R');
        self.op(b't').op(b'R')
    }
    /// `OrderedDict()` followed by SETITEMS of `(name, tensor)` pairs.
    fn state_dict(&mut self, items: &[Item]) -> &mut Self {
        self.global("collections", "OrderedDict")
            .op(b')')
            .op(b'R')
            .op(b'(');
        for (name, s, offset, size, stride) in items {
            self.str(name).tensor(s, *offset, size, stride);
        }
        self.op(b'u')
    }
    fn stop(&mut self) -> Vec<u8> {
        self.op(b'.');
        std::mem::take(&mut self.0)
    }
}

/// A state dict entry: name, storage, storage offset, size, stride.
type Item<'a> = (&'a str, &'a StorageSpec, i64, &'a [i64], &'a [i64]);

/// A storage persistent id.
struct StorageSpec {
    class: &'static str,
    key: &'static str,
    numel: i64,
    view: Option<(&'static str, i64, i64)>,
    /// Legacy ids have a sixth field (view metadata or None).
    legacy: bool,
}

fn storage(class: &'static str, key: &'static str, numel: i64, legacy: bool) -> StorageSpec {
    StorageSpec {
        class,
        key,
        numel,
        view: None,
        legacy,
    }
}

/// A legacy-format file: header pickles, the main pickle, the key list, then the storages.
fn legacy_file(main: &[u8], storages: &[(&str, u64, Vec<u8>)], little_endian: bool) -> Vec<u8> {
    let mut out = Vec::new();
    let magic: u128 = 0x1950_a86a_20f9_469c_fc6c;
    out.extend(
        Pickler::new(2)
            .op(0x8a)
            .op(10)
            .raw(&magic.to_le_bytes()[..10])
            .stop(),
    );
    out.extend(Pickler::new(2).op(b'M').raw(&1001u16.to_le_bytes()).stop());
    let mut info = Pickler::new(2);
    info.op(b'}').op(b'(').str("protocol_version").int(1001);
    info.str("little_endian")
        .op(if little_endian { 0x88 } else { 0x89 });
    out.extend(info.op(b'u').stop());
    out.extend_from_slice(main);
    let mut keys = Pickler::new(2);
    keys.op(b']').op(b'(');
    for (key, _, _) in storages {
        keys.str(key);
    }
    out.extend(keys.op(b'e').stop());
    for (_, count, bytes) in storages {
        out.extend_from_slice(&count.to_le_bytes());
        out.extend_from_slice(bytes);
    }
    out
}

/// CRC-32 (IEEE), bit by bit.
fn crc32_bitwise(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A stored (uncompressed) zip archive without zip64 records, as APPNOTE 4.3 lays it out.
/// Returns the archive and the file offset of each entry's data.
fn zip_file(entries: &[(String, Vec<u8>)]) -> (Vec<u8>, Vec<usize>) {
    let mut out = Vec::new();
    let mut central = Vec::new();
    let mut offsets = Vec::new();
    for (name, data) in entries {
        let local = out.len() as u32;
        let crc = crc32_bitwise(data);
        let fixed = |sig: u32, out: &mut Vec<u8>| {
            out.extend_from_slice(&sig.to_le_bytes());
            if sig == 0x0201_4b50 {
                out.extend_from_slice(&20u16.to_le_bytes()); // version made by
            }
            out.extend_from_slice(&20u16.to_le_bytes()); // version needed
            out.extend_from_slice(&0u16.to_le_bytes()); // flags
            out.extend_from_slice(&0u16.to_le_bytes()); // method: stored
            out.extend_from_slice(&[0; 4]); // time, date
            out.extend_from_slice(&crc.to_le_bytes());
            out.extend_from_slice(&(data.len() as u32).to_le_bytes());
            out.extend_from_slice(&(data.len() as u32).to_le_bytes());
            out.extend_from_slice(&(name.len() as u16).to_le_bytes());
            out.extend_from_slice(&0u16.to_le_bytes()); // extra length
        };
        fixed(0x0403_4b50, &mut out);
        out.extend_from_slice(name.as_bytes());
        offsets.push(out.len());
        out.extend_from_slice(data);
        fixed(0x0201_4b50, &mut central);
        central.extend_from_slice(&[0; 10]); // comment length, disk, internal and external attributes
        central.extend_from_slice(&local.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
    }
    let cd_offset = out.len() as u32;
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    out.extend_from_slice(&[0; 4]); // disk numbers
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    out.extend_from_slice(&(central.len() as u32).to_le_bytes());
    out.extend_from_slice(&cd_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes()); // comment length
    (out, offsets)
}

/// A zip-format checkpoint named `top` with this pickle and these storages.
fn zip_checkpoint(
    top: &str,
    pickle: Vec<u8>,
    storages: &[(&str, Vec<u8>)],
    order: &str,
) -> Vec<u8> {
    let mut entries = vec![(format!("{top}/data.pkl"), pickle)];
    entries.push((format!("{top}/byteorder"), order.as_bytes().to_vec()));
    for (key, bytes) in storages {
        entries.push((format!("{top}/data/{key}"), bytes.clone()));
    }
    entries.push((format!("{top}/version"), b"3\n".to_vec()));
    zip_file(&entries).0
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn tensor(shape: &[usize], data: &[f32]) -> TensorF32 {
    TensorF32::new(shape.to_vec(), data.to_vec()).expect("consistent test tensor")
}

fn shared(rel: &str) -> PathBuf {
    shared_path(rel)
}

fn read(rel: &str) -> Vec<u8> {
    std::fs::read(shared(rel)).expect("shared fixture is readable")
}

// ---------------------------------------------------------------------------------------------
// Fixtures and real weights
// ---------------------------------------------------------------------------------------------

#[test]
fn fixture_checkpoints_equal_safetensors_bitwise() {
    let reference = Fixture::shared("oracle/fixtures/checkpoints.safetensors");
    for net in ["vgg", "decoder"] {
        let prefix = format!("{net}.");
        let expected: BTreeMap<&str, _> = reference
            .names()
            .into_iter()
            .filter_map(|n| n.strip_prefix(&prefix).map(|k| (k, reference.get(n))))
            .collect();
        assert!(
            !expected.is_empty(),
            "no {net}.* tensors in checkpoints.safetensors"
        );
        for format in ["legacy", "zip"] {
            let file = format!("oracle/fixtures/{net}_{format}.pth");
            let sd = load_checkpoint(&shared(&file)).unwrap_or_else(|e| panic!("{e}"));
            let keys: Vec<&str> = sd.keys().map(String::as_str).collect();
            let want: Vec<&str> = expected.keys().copied().collect();
            assert_eq!(keys, want, "{file}: tensor names");
            for (k, t) in &sd {
                let e = expected[k.as_str()];
                assert_eq!(t.shape, e.shape, "{file}: shape of {k}");
                let same = t
                    .data
                    .iter()
                    .zip(e.to_f32())
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(
                    same && t.data.len() == e.data.len(),
                    "{file}: values of {k} differ"
                );
            }
        }
    }
}

/// Name, shape, f64 sum, f64 sum of magnitudes, bits of the first and last element.
type Fingerprint = (&'static str, &'static [usize], f64, f64, u32, u32);

/// Keys, shapes, f64 sum, f64 sum of magnitudes, and the bits of the first and last element of
/// every tensor of the real weights, as reported by `torch.load` (PyTorch 2.15) on these files.
#[rustfmt::skip]
const REAL_WEIGHTS: &[(&str, &[Fingerprint])] = &[
    (
        "compressed-16x-relu4_1/4SD.pth",
        &[
            ("conv11.bias", &[3], 0.14315766841173172, 0.14315766841173172, 0x3d41e627, 0x3d0d279b),
            ("conv11.weight", &[3, 16, 3, 3], 3.9465645824984676, 29.30859384442556, 0x3c76e8c9, 0x3e1b36e3),
            ("conv12.bias", &[16], -0.07974714739248157, 0.3755623851902783, 0xbb185998, 0x3c628a5c),
            ("conv12.weight", &[16, 16, 3, 3], -17.039912666696182, 131.4454960042567, 0xbce0ce87, 0xbc6c1e8f),
            ("conv21.bias", &[16], 0.10713169747032225, 0.4496062605176121, 0xbd0761c3, 0x3b762c65),
            ("conv21.weight", &[16, 32, 3, 3], -13.347932620586562, 183.8966099319664, 0xbc09be3a, 0xbdf70abb),
            ("conv22.bias", &[32], 0.1582268147612922, 0.8424533989164047, 0xbb3b008d, 0xbd319bb7),
            ("conv22.weight", &[32, 32, 3, 3], -13.08889557850307, 294.4506189562853, 0xbc5eb3b2, 0x3b14430c),
            ("conv31.bias", &[32], 0.5035816844319925, 1.113760792533867, 0xbce08f14, 0x3d83466a),
            ("conv31.weight", &[32, 64, 3, 3], 12.731534230048965, 453.9510935633234, 0xbb8b9b80, 0xbd5a9c1a),
            ("conv32.bias", &[64], 1.7066122431715485, 3.04020781753934, 0x3da0cae2, 0xbd780d02),
            ("conv32.weight", &[64, 64, 3, 3], -2.295723960387974, 858.7030724665874, 0x3c6501bc, 0xbd3afd0c),
            ("conv33.bias", &[64], 1.9480278605478816, 3.4095535545493476, 0x3cc8754f, 0xbdc70b9d),
            ("conv33.weight", &[64, 64, 3, 3], 1.0483051413633007, 706.2918752689686, 0xbaf659e8, 0xbba9048b),
            ("conv34.bias", &[64], 1.3865183215384604, 3.6985188327525975, 0x3cce594b, 0xbd2d8743),
            ("conv34.weight", &[64, 64, 3, 3], 4.017498351279187, 592.354864623513, 0xbc206087, 0xbb6213e1),
            ("conv41.bias", &[64], 2.4202923516045303, 4.861632648645809, 0xbaa0353a, 0xbcd288f1),
            ("conv41.weight", &[64, 128, 3, 3], 7.817420226292995, 794.975441881021, 0x3c3a041d, 0x3ace4f33),
        ],
    ),
    (
        "compressed-16x-relu4_1/4SE.pth",
        &[
            ("conv0.bias", &[3], -344.20330810546875, 344.20330810546875, 0xc2cf3028, 0xc2f7957c),
            ("conv0.weight", &[3, 3, 1, 1], 765.7289031576365, 766.1120094228536, 0x3eaa812b, 0xbd6dfaf7),
            ("conv11.bias", &[16], 6.008419282734394, 7.773298524320126, 0xbf4ee108, 0x3f19bbce),
            ("conv11.weight", &[16, 3, 3, 3], -0.30787040689938294, 11.781042076889207, 0xbc74d87e, 0xbd24f4ae),
            ("conv11_aux.bias", &[64], -5.621229865108035, 7.020844969913014, 0xbe2915c6, 0xbe0b1e8b),
            ("conv11_aux.weight", &[64, 16, 1, 1], 21.77592820790869, 47.68188497644678, 0x3abf25d3, 0xbd5640f5),
            ("conv12.bias", &[16], 2.4585087932646275, 2.7638045251369476, 0x3d270ba7, 0x3e906f81),
            ("conv12.weight", &[16, 16, 3, 3], 30.096126482459113, 122.07633572584109, 0x3dd38d1e, 0x3d7678a4),
            ("conv21.bias", &[32], 1.2472985201748088, 3.448100490611978, 0xbd5178d8, 0xbc83a062),
            ("conv21.weight", &[32, 16, 3, 3], 23.35519571829832, 111.53970132617837, 0xbc26c17c, 0xbc78c33d),
            ("conv21_aux.bias", &[128], -9.139503845013678, 14.219022133853287, 0xbebcef1d, 0x3cd75152),
            ("conv21_aux.weight", &[128, 32, 1, 1], 9.837070464931458, 253.13841949480047, 0xbc9e4984, 0xbd831092),
            ("conv22.bias", &[32], 1.4414859014796093, 2.955329248565249, 0xba447d26, 0xbd6a1c45),
            ("conv22.weight", &[32, 32, 3, 3], 10.115709070408514, 241.22863822010305, 0xbcd3301a, 0x3a0e91c6),
            ("conv31.bias", &[64], 1.4559479249073775, 5.89420342984522, 0xbba70dc0, 0x3b497dda),
            ("conv31.weight", &[64, 32, 3, 3], 46.96766612622423, 593.0973960007809, 0xbc2c6238, 0x3b54f9e6),
            ("conv31_aux.bias", &[256], -12.988904483383521, 37.297781171509996, 0xbda8e22a, 0xbe1ba0d4),
            ("conv31_aux.weight", &[256, 64, 1, 1], 62.64664502866549, 934.7040588500447, 0x3ddc81a2, 0x3b881616),
            ("conv32.bias", &[64], 3.0623897747973388, 4.588831451223086, 0x3db45b8b, 0x3b91df7c),
            ("conv32.weight", &[64, 64, 3, 3], -12.245557334038736, 560.6502690446348, 0x3b8815dd, 0x3d8c8e78),
            ("conv33.bias", &[64], 2.7311494308523834, 3.6691821170970798, 0x3df6bb47, 0x3d9484e0),
            ("conv33.weight", &[64, 64, 3, 3], -10.914886242095825, 499.34956968814305, 0xbd21c7de, 0x3b750127),
            ("conv34.bias", &[64], 1.8180893405515235, 2.878674192907056, 0x3d979fc2, 0x3d049998),
            ("conv34.weight", &[64, 64, 3, 3], -20.18477417164044, 580.0435178822017, 0x3d29322f, 0xbd140109),
            ("conv41.bias", &[128], 0.7622481369362504, 4.620775880193833, 0xba5ed710, 0xb9af0294),
            ("conv41.weight", &[128, 64, 3, 3], -136.35330194117026, 833.5574073318373, 0x3c9004a5, 0xbc818489),
            ("conv41_aux.bias", &[512], -3.5813918712665327, 79.77060854336014, 0xbe68d22e, 0xbb2b65b1),
            ("conv41_aux.weight", &[512, 128, 1, 1], 68.57368178524143, 2996.9765697692005, 0x3daeb462, 0x3ce59b9e),
        ],
    ),
    (
        "wct-relu1_1-3_1/feature_invertor_conv1_1.pth",
        &[
            ("1.bias", &[3], 1.2138826251029968, 1.2138826251029968, 0x3ee0d66c, 0x3eb9c9ea),
            ("1.weight", &[3, 64, 3, 3], 0.07538582966844842, 20.79731296115824, 0xbc756a39, 0x3c5a3141),
        ],
    ),
    (
        "wct-relu1_1-3_1/feature_invertor_conv2_1.pth",
        &[
            ("1.bias", &[64], 1.4254034453770146, 5.360185142955743, 0xbdb2591b, 0x3db37b61),
            ("1.weight", &[64, 128, 3, 3], 19.653086136549234, 967.3766938237145, 0xbc2b2ba7, 0xba2526df),
            ("5.bias", &[64], 0.20256506215082482, 4.351740358688403, 0x3add4cdf, 0xbdeb8c72),
            ("5.weight", &[64, 64, 3, 3], -0.7660690755154178, 726.6805677609848, 0x3cb3484f, 0xbc73a77b),
            ("8.bias", &[3], 0.15166247263550758, 0.15166247263550758, 0x3d040995, 0x3d978d84),
            ("8.weight", &[3, 64, 3, 3], 1.4335565685714755, 30.658620539380536, 0x3c4d116e, 0xbcde0a70),
        ],
    ),
    (
        "wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
        &[
            ("1.bias", &[128], 1.6678409637970617, 8.049655729308142, 0x3d929a1c, 0x3d5832fb),
            ("1.weight", &[128, 256, 3, 3], 156.52044683172676, 2885.732152713763, 0xbc86f896, 0x3d1964e7),
            ("12.bias", &[64], 0.9404481146484613, 2.733458699192852, 0x3d050216, 0xbcb59ca1),
            ("12.weight", &[64, 64, 3, 3], -17.995146958636724, 775.2230899798769, 0xbd5ad06a, 0x3d2e974a),
            ("15.bias", &[3], 0.09616862121038139, 0.0990504112560302, 0x3d604a93, 0x3d2f846c),
            ("15.weight", &[3, 64, 3, 3], 1.9405430947244895, 41.03151226680893, 0x3c0a5629, 0x3bd07e54),
            ("5.bias", &[128], 2.088698524836218, 8.22049151934334, 0x3db016f9, 0x3d2c348a),
            ("5.weight", &[128, 128, 3, 3], 31.523739802924524, 2109.722141807389, 0x3c8b04af, 0x3bb8b3fb),
            ("8.bias", &[64], 1.4699042972642928, 3.507435654406436, 0x3cd7fe21, 0xbd9b84bd),
            ("8.weight", &[64, 128, 3, 3], 14.740608445556916, 1068.243713465933, 0xbcd5e805, 0xbc96d680),
        ],
    ),
    (
        "wct-relu1_1-3_1/vgg_normalised_conv1_1.pth",
        &[
            ("0.bias", &[3], -344.3980026245117, 344.3980026245117, 0xc2cfe0c5, 0xc2f75c29),
            ("0.weight", &[3, 3, 1, 1], 765.0, 765.0, 0x00000000, 0x00000000),
            ("2.bias", &[64], 1.579187505878508, 1.5815938357263803, 0x3d1614d7, 0x3cb2f7ed),
            ("2.weight", &[64, 3, 3, 3], -0.14005323064998265, 15.89707582882943, 0x3c8c425b, 0xbc69b5f5),
        ],
    ),
    (
        "wct-relu1_1-3_1/vgg_normalised_conv2_1.pth",
        &[
            ("0.bias", &[3], -344.3980026245117, 344.3980026245117, 0xc2cfe0c5, 0xc2f75c29),
            ("0.weight", &[3, 3, 1, 1], 765.0, 765.0, 0x00000000, 0x00000000),
            ("2.bias", &[64], 1.579187505878508, 1.5815938357263803, 0x3d1614d7, 0x3cb2f7ed),
            ("2.weight", &[64, 3, 3, 3], -0.14005323064998265, 15.89707582882943, 0x3c8c425b, 0xbc69b5f5),
            ("5.bias", &[64], -0.03829649979888927, 0.256807425947045, 0xbbb630bc, 0xbc493a8e),
            ("5.weight", &[64, 64, 3, 3], 32.10781618619035, 312.9534983448907, 0x3d665578, 0x3c1c4ddc),
            ("9.bias", &[128], 0.07231692886853125, 0.15141767375462223, 0xbad2302e, 0x3a869182),
            ("9.weight", &[128, 64, 3, 3], -62.37655218779952, 1293.3576934445914, 0xbb9be3a1, 0xbaff868e),
        ],
    ),
    (
        "wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
        &[
            ("0.bias", &[3], -344.3980026245117, 344.3980026245117, 0xc2cfe0c5, 0xc2f75c29),
            ("0.weight", &[3, 3, 1, 1], 765.0, 765.0, 0x00000000, 0x00000000),
            ("12.bias", &[128], 0.0023073574875525082, 0.18435758282157622, 0xba6cd75c, 0x3b0bb777),
            ("12.weight", &[128, 128, 3, 3], -106.34074952128509, 3078.129050983417, 0xb94307a2, 0x3baceb5f),
            ("16.bias", &[256], 0.03902319904166873, 0.11601598013233527, 0x3985748f, 0x3a351166),
            ("16.weight", &[256, 128, 3, 3], -118.41515333914833, 3464.241717329483, 0xbb3d5783, 0x3c8845bc),
            ("2.bias", &[64], 1.579187505878508, 1.5815938357263803, 0x3d1614d7, 0x3cb2f7ed),
            ("2.weight", &[64, 3, 3, 3], -0.14005323064998265, 15.89707582882943, 0x3c8c425b, 0xbc69b5f5),
            ("5.bias", &[64], -0.03829649979888927, 0.256807425947045, 0xbbb630bc, 0xbc493a8e),
            ("5.weight", &[64, 64, 3, 3], 32.10781618619035, 312.9534983448907, 0x3d665578, 0x3c1c4ddc),
            ("9.bias", &[128], 0.07231692886853125, 0.15141767375462223, 0xbad2302e, 0x3a869182),
            ("9.weight", &[128, 64, 3, 3], -62.37655218779952, 1293.3576934445914, 0xbb9be3a1, 0xbaff868e),
        ],
    ),
];

#[test]
fn real_weights_match_torch_fingerprints() {
    for (file, tensors) in REAL_WEIGHTS {
        let path = shared(&format!("weights/{file}"));
        let sd = load_checkpoint(&path).unwrap_or_else(|e| panic!("{e}"));
        let keys: Vec<&str> = sd.keys().map(String::as_str).collect();
        let want: Vec<&str> = tensors.iter().map(|t| t.0).collect();
        assert_eq!(keys, want, "{file}: tensor names");
        for &(key, shape, sum, abs_sum, first, last) in tensors.iter() {
            let t = &sd[key];
            assert_eq!(t.shape, shape, "{file}: shape of {key}");
            assert_eq!(t.data[0].to_bits(), first, "{file}: first element of {key}");
            assert_eq!(
                t.data[t.numel() - 1].to_bits(),
                last,
                "{file}: last element of {key}"
            );
            // Both sums add the same f32 values in f64, in different orders; the difference is
            // at most 2 n eps_64 sum|x| < 1e-10 sum|x| for the n < 3e5 elements of any tensor.
            let s: f64 = t.data.iter().map(|&x| f64::from(x)).sum();
            let a: f64 = t.data.iter().map(|&x| f64::from(x).abs()).sum();
            assert!(
                (a - abs_sum).abs() <= 1e-10 * abs_sum,
                "{file}: sum |x| of {key}: {a} vs {abs_sum}"
            );
            assert!(
                (s - sum).abs() <= 1e-10 * abs_sum,
                "{file}: sum of {key}: {s} vs {sum}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Hand-built checkpoints
// ---------------------------------------------------------------------------------------------

#[test]
fn dtypes_strides_offsets_and_views_in_legacy_format() {
    // Storage "f": 0..6 as f32. "t" is its transpose view, "o" a 2x2 window at offset 1.
    let f = storage("FloatStorage", "f", 6, true);
    // Float16: 1, -2, 0.5, 65504 (largest), 2^-24 (smallest subnormal), -0.
    let h = storage("HalfStorage", "h", 6, true);
    let h_bits: [u16; 6] = [0x3c00, 0xc000, 0x3800, 0x7bff, 0x0001, 0x8000];
    // BFloat16: 1, -3, 2^-126 (smallest normal).
    let b = storage("BFloat16Storage", "b", 3, true);
    let b_bits: [u16; 3] = [0x3f80, 0xc040, 0x0080];
    // Float64: 0.1 rounds to the nearest f32; 1e300 overflows to infinity.
    let d = storage("DoubleStorage", "d", 2, true);
    // A legacy storage view: elements 2..5 of root "r".
    let mut r = storage("FloatStorage", "r", 6, true);
    r.view = Some(("r_view", 2, 3));
    // An int64 buffer (skipped).
    let l = storage("LongStorage", "l", 1, true);

    let main = Pickler::new(2)
        .state_dict(&[
            ("t", &f, 0, &[3, 2], &[1, 3]),
            ("o", &f, 1, &[2, 2], &[1, 3]),
            ("h", &h, 0, &[2, 3], &[3, 1]),
            ("b", &b, 0, &[3], &[1]),
            ("d", &d, 0, &[2], &[1]),
            ("v", &r, 1, &[2], &[1]),
            ("scalar", &f, 5, &[], &[]),
            ("empty", &f, 0, &[0, 4], &[4, 1]),
            ("num_batches_tracked", &l, 0, &[], &[]),
        ])
        .stop();
    let le16 = |v: &[u16]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let doubles: Vec<u8> = [0.1f64, 1e300]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    let file = legacy_file(
        &main,
        &[
            ("f", 6, f32_bytes(&[0., 1., 2., 3., 4., 5.])),
            ("h", 6, le16(&h_bits)),
            ("b", 3, le16(&b_bits)),
            ("d", 2, doubles),
            ("r", 6, f32_bytes(&[10., 11., 12., 13., 14., 15.])),
            ("l", 1, 7i64.to_le_bytes().to_vec()),
        ],
        true,
    );
    let sd = load_checkpoint_bytes(&file).unwrap_or_else(|e| panic!("{e}"));
    let mut want = StateDict::new();
    want.insert("t".into(), tensor(&[3, 2], &[0., 3., 1., 4., 2., 5.]));
    want.insert("o".into(), tensor(&[2, 2], &[1., 4., 2., 5.]));
    let sub = 2f32.powi(-24);
    want.insert(
        "h".into(),
        tensor(&[2, 3], &[1., -2., 0.5, 65504., sub, -0.]),
    );
    want.insert("b".into(), tensor(&[3], &[1., -3., f32::MIN_POSITIVE]));
    want.insert("d".into(), tensor(&[2], &[0.1f32, f32::INFINITY]));
    want.insert("v".into(), tensor(&[2], &[13., 14.]));
    want.insert("scalar".into(), tensor(&[], &[5.]));
    want.insert("empty".into(), tensor(&[0, 4], &[]));
    assert_eq!(sd, want);
    assert!(
        sd["h"].data[5].is_sign_negative(),
        "float16 -0 keeps its sign"
    );
}

#[test]
fn big_endian_storages_are_byte_swapped() {
    let f = storage("FloatStorage", "0", 2, true);
    let main = Pickler::new(2)
        .state_dict(&[("w", &f, 0, &[2], &[1])])
        .stop();
    let be: Vec<u8> = [1.5f32, -7.25]
        .iter()
        .flat_map(|x| x.to_be_bytes())
        .collect();
    let legacy = legacy_file(&main, &[("0", 2, be.clone())], false);
    let sd = load_checkpoint_bytes(&legacy).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(sd["w"], tensor(&[2], &[1.5, -7.25]));

    let f = storage("FloatStorage", "0", 2, false);
    let pkl = Pickler::new(2)
        .state_dict(&[("w", &f, 0, &[2], &[1])])
        .stop();
    let zip = zip_checkpoint("archive", pkl, &[("0", be)], "big");
    let sd = load_checkpoint_bytes(&zip).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(sd["w"], tensor(&[2], &[1.5, -7.25]));
}

#[test]
fn protocol_4_opcodes_wrappers_and_nesting_in_zip_format() {
    // {'model': OrderedDict(w=tensor), 'epoch': 20} with FRAME, SHORT_BINUNICODE, STACK_GLOBAL,
    // MEMOIZE and BINGET, as pickle protocol 4 writes them.
    let s = storage("FloatStorage", "0", 3, false);
    let mut p = Pickler::new(4);
    p.op(0x95).raw(&0u64.to_le_bytes()); // FRAME (length is only a hint)
    p.op(b'}').op(0x94).op(b'('); // {  memo 0
    p.op(0x8c).op(5).raw(b"model");
    p.op(0x8c)
        .op(11)
        .raw(b"collections")
        .op(0x8c)
        .op(11)
        .raw(b"OrderedDict");
    p.op(0x93).op(0x94).op(b')').op(b'R'); // STACK_GLOBAL, memo 1, OrderedDict()
    p.op(0x8c)
        .op(6)
        .raw(b"weight")
        .tensor(&s, 0, &[3], &[1])
        .op(b's');
    // A parameter: _rebuild_parameter(tensor, True, OrderedDict()).
    p.op(0x8c).op(4).raw(b"bias");
    p.global("torch._utils", "_rebuild_parameter").op(b'(');
    p.tensor(&s, 1, &[2], &[1])
        .op(0x88)
        .op(b'h')
        .op(1)
        .op(b')')
        .op(b'R')
        .op(b't')
        .op(b'R');
    p.op(b's');
    p.op(0x8c).op(5).raw(b"epoch").op(b'K').op(20);
    let pkl = p.op(b'u').stop();
    let zip = zip_checkpoint("ckpt", pkl, &[("0", f32_bytes(&[1., 2., 3.]))], "little");
    let sd = load_checkpoint_bytes(&zip).unwrap_or_else(|e| panic!("{e}"));
    let mut want = StateDict::new();
    want.insert("weight".into(), tensor(&[3], &[1., 2., 3.]));
    want.insert("bias".into(), tensor(&[2], &[2., 3.]));
    assert_eq!(
        sd, want,
        "the 'model' wrapper is unwrapped, 'epoch' ignored"
    );

    // Without a known wrapper key, nested dicts flatten with dotted names (int keys in decimal).
    let mut p = Pickler::new(2);
    p.op(b'}')
        .op(b'(')
        .str("enc")
        .op(b'}')
        .op(b'(')
        .op(b'K')
        .op(3);
    p.tensor(&s, 0, &[1], &[1]).op(b'u');
    p.str("top")
        .tensor(&s, 2, &[1], &[1])
        .str("note")
        .str("text")
        .op(b'u');
    let zip = zip_checkpoint("x", p.stop(), &[("0", f32_bytes(&[1., 2., 3.]))], "little");
    let sd = load_checkpoint_bytes(&zip).unwrap_or_else(|e| panic!("{e}"));
    let mut want = StateDict::new();
    want.insert("enc.3".into(), tensor(&[1], &[1.]));
    want.insert("top".into(), tensor(&[1], &[3.]));
    assert_eq!(sd, want);
}

#[test]
fn f16_conversion_covers_special_values() {
    let s = storage("HalfStorage", "0", 4, false);
    let pkl = Pickler::new(2)
        .state_dict(&[("h", &s, 0, &[4], &[1])])
        .stop();
    // +inf, -inf, NaN, 0.333251953125 (0x3555 = 1.0101010101b x 2^-2).
    let bits: [u16; 4] = [0x7c00, 0xfc00, 0x7e00, 0x3555];
    let bytes: Vec<u8> = bits.iter().flat_map(|x| x.to_le_bytes()).collect();
    let sd = load_checkpoint_bytes(&zip_checkpoint("a", pkl, &[("0", bytes)], "little"))
        .unwrap_or_else(|e| panic!("{e}"));
    let h = &sd["h"].data;
    assert_eq!(h[0], f32::INFINITY);
    assert_eq!(h[1], f32::NEG_INFINITY);
    assert!(h[2].is_nan());
    assert_eq!(h[3], 0.333_251_95);
}

// ---------------------------------------------------------------------------------------------
// Hostile and broken input
// ---------------------------------------------------------------------------------------------

/// The classic exploit: `os.system('echo pwned')` via GLOBAL + REDUCE.
fn os_system_pickle() -> Vec<u8> {
    let mut p = Pickler::new(2);
    p.global("os", "system").str("echo pwned").op(0x85).op(b'R');
    p.stop()
}

#[test]
fn malicious_global_is_rejected_with_its_offset() {
    let bad = os_system_pickle();
    let unsupported = |module: &str, name: &str, offset: u64| FormatError::UnsupportedGlobal {
        module: module.into(),
        name: name.into(),
        offset,
    };
    // As a bare pickle (read as a legacy file): GLOBAL is at byte 2.
    assert_eq!(
        load_checkpoint_bytes(&bad),
        Err(unsupported("os", "system", 2))
    );

    // As the main pickle of a well-formed legacy file.
    let file = legacy_file(&bad, &[], true);
    let at = file.windows(bad.len()).position(|w| w == bad).unwrap() as u64;
    assert_eq!(
        load_checkpoint_bytes(&file),
        Err(unsupported("os", "system", at + 2))
    );

    // As data.pkl of a zip checkpoint: the offset is counted from the start of the file.
    let (zip, offsets) = zip_file(&[("a/data.pkl".into(), bad.clone())]);
    let want = unsupported("os", "system", offsets[0] as u64 + 2);
    assert_eq!(load_checkpoint_bytes(&zip), Err(want.clone()));
    let msg = want.to_string();
    assert!(msg.contains("os.system") && msg.contains("byte"), "{msg}");

    // STACK_GLOBAL (protocol 4) is checked too.
    let mut p = Pickler::new(4);
    p.op(0x8c)
        .op(8)
        .raw(b"builtins")
        .op(0x8c)
        .op(4)
        .raw(b"eval")
        .op(0x93);
    assert_eq!(
        load_checkpoint_bytes(&p.stop()),
        Err(unsupported("builtins", "eval", 18))
    );

    // A whitelisted-looking module with another name.
    let mut p = Pickler::new(2);
    p.global("torch._utils", "_load_from_bytes");
    assert_eq!(
        load_checkpoint_bytes(&p.stop()),
        Err(unsupported("torch._utils", "_load_from_bytes", 2))
    );
}

#[test]
fn code_running_opcodes_are_rejected() {
    // INST, OBJ, NEWOBJ, EXT1, and a byte that is no opcode at all.
    for op in [b'i', b'o', 0x81, 0x82, 0xff] {
        let bytes = Pickler::new(2).op(b'N').op(op).stop();
        assert_eq!(
            load_checkpoint_bytes(&bytes),
            Err(FormatError::UnsupportedOpcode {
                opcode: op,
                offset: 3
            }),
            "opcode {op:#04x}"
        );
    }
    let msg = FormatError::UnsupportedOpcode {
        opcode: b'i',
        offset: 3,
    }
    .to_string();
    assert!(msg.contains("INST") && msg.contains("byte 3"), "{msg}");
}

#[test]
fn absurd_sizes_fail_before_allocating() {
    // A 4 GiB string length in a 12-byte file.
    let bytes = Pickler::new(2).op(b'X').raw(&u32::MAX.to_le_bytes()).stop();
    assert!(matches!(
        load_checkpoint_bytes(&bytes),
        Err(FormatError::Truncated { .. })
    ));

    // A legacy storage declaring 2^61 float32 elements, with a matching count in the file.
    let huge = 1i64 << 61;
    let s = storage("FloatStorage", "0", huge, true);
    let main = Pickler::new(2)
        .state_dict(&[("w", &s, 0, &[huge], &[1])])
        .stop();
    let file = legacy_file(&main, &[("0", huge as u64, vec![0; 16])], true);
    match load_checkpoint_bytes(&file) {
        Err(FormatError::Truncated { what, .. }) => assert!(what.contains("storage 0"), "{what}"),
        other => panic!("expected a truncation error, got {other:?}"),
    }

    // A zip storage entry smaller than its declared size.
    let s = storage("FloatStorage", "0", 1000, false);
    let pkl = Pickler::new(2)
        .state_dict(&[("w", &s, 0, &[1000], &[1])])
        .stop();
    let zip = zip_checkpoint("a", pkl, &[("0", vec![0; 16])], "little");
    assert!(
        matches!(load_checkpoint_bytes(&zip), Err(FormatError::Storage { key, .. }) if key == "0")
    );

    // A broadcast view (stride 0) of one element claiming 2^40 elements.
    let s = storage("FloatStorage", "0", 1, true);
    let main = Pickler::new(2)
        .state_dict(&[("w", &s, 0, &[1 << 40], &[0])])
        .stop();
    let file = legacy_file(&main, &[("0", 1, f32_bytes(&[1.]))], true);
    assert!(
        matches!(load_checkpoint_bytes(&file), Err(FormatError::Tensor { name, .. }) if name == "w")
    );

    // Tuples nested 100 deep.
    let mut p = Pickler::new(2);
    p.op(b')');
    for _ in 0..100 {
        p.op(0x85);
    }
    assert!(matches!(
        load_checkpoint_bytes(&p.stop()),
        Err(FormatError::Limit { .. })
    ));

    // More stack values than the limit.
    let mut p = Pickler::new(2);
    p.raw(&vec![b'N'; (1 << 20) + 1]);
    assert!(matches!(
        load_checkpoint_bytes(&p.stop()),
        Err(FormatError::Limit { .. })
    ));

    // A memo index of 2^32 - 1 costs one entry, not a 4 G-entry table.
    let mut p = Pickler::new(2);
    p.op(b'N')
        .op(b'r')
        .raw(&u32::MAX.to_le_bytes())
        .op(b'j')
        .raw(&u32::MAX.to_le_bytes());
    assert!(matches!(
        load_checkpoint_bytes(&p.stop()),
        Err(FormatError::Header { .. })
    ));
}

#[test]
fn layout_errors_name_the_tensor_or_storage() {
    let s = storage("FloatStorage", "0", 4, true);
    // Offset 2 + 3 elements reach past a 4-element storage.
    let main = Pickler::new(2)
        .state_dict(&[("layer.weight", &s, 2, &[3], &[1])])
        .stop();
    let file = legacy_file(&main, &[("0", 4, f32_bytes(&[0.; 4]))], true);
    let err = load_checkpoint_bytes(&file).unwrap_err();
    assert!(
        matches!(&err, FormatError::Tensor { name, .. } if name == "layer.weight"),
        "{err}"
    );

    // A storage whose data is not in the file.
    let file = legacy_file(&main, &[], true);
    assert_eq!(
        load_checkpoint_bytes(&file),
        Err(FormatError::MissingStorage { key: "0".into() })
    );
    let s = storage("FloatStorage", "0", 4, false);
    let pkl = Pickler::new(2)
        .state_dict(&[("w", &s, 0, &[4], &[1])])
        .stop();
    let zip = zip_checkpoint("a", pkl, &[], "little");
    assert_eq!(
        load_checkpoint_bytes(&zip),
        Err(FormatError::MissingStorage { key: "0".into() })
    );

    // An element count in the file that differs from the pickle's.
    let file = legacy_file(&main, &[("0", 3, f32_bytes(&[0.; 3]))], true);
    assert!(matches!(
        load_checkpoint_bytes(&file),
        Err(FormatError::Storage { .. })
    ));

    // A top-level object that is not a dict.
    let file = legacy_file(&Pickler::new(2).op(b'N').stop(), &[], true);
    assert!(matches!(
        load_checkpoint_bytes(&file),
        Err(FormatError::Layout { .. })
    ));

    // Neither zip nor pickle.
    let err = load_checkpoint_bytes(b"GIF89a").unwrap_err();
    assert_eq!(
        err,
        FormatError::UnknownFormat {
            found: b"GIF8".to_vec()
        }
    );
}

#[test]
fn shared_or_cyclic_dicts_and_huge_keys_are_refused() {
    let layout = |pickle: Vec<u8>| {
        let zip = zip_checkpoint("a", pickle, &[], "little");
        matches!(load_checkpoint_bytes(&zip), Err(FormatError::Layout { .. }))
    };
    // A dict that contains itself: {'a': <itself>}.
    let mut p = Pickler::new(2);
    p.op(b'}').op(b'q').op(0).str("a").op(b'h').op(0).op(b's');
    assert!(layout(p.stop()));
    // The same inner dict under two keys, nested: 2^30 paths if it were expanded.
    let mut p = Pickler::new(2);
    p.op(b'}').op(b'q').op(0);
    for level in 1..=30u8 {
        p.op(b'}')
            .op(b'q')
            .op(level)
            .str("x")
            .op(b'h')
            .op(level - 1)
            .op(b's');
        p.str("y").op(b'h').op(level - 1).op(b's');
    }
    assert!(layout(p.stop()));
    // A 2 kB dict key.
    let mut p = Pickler::new(2);
    p.op(b'}').str(&"k".repeat(2048)).op(b'N').op(b's');
    let zip = zip_checkpoint("a", p.stop(), &[], "little");
    assert!(matches!(
        load_checkpoint_bytes(&zip),
        Err(FormatError::Limit { .. })
    ));
}

#[test]
fn file_errors_name_the_file() {
    let missing = std::env::temp_dir().join("dsgs-no-such-checkpoint.pth");
    let err = load_checkpoint(&missing).unwrap_err();
    assert!(matches!(err, CheckpointError::Io { .. }));
    assert!(
        err.to_string().contains("dsgs-no-such-checkpoint.pth"),
        "{err}"
    );

    // A real file, corrupted: the message names it.
    let dir = std::env::temp_dir().join(format!("dsgs-checkpoint-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bad.pth");
    std::fs::write(&path, os_system_pickle()).unwrap();
    let err = load_checkpoint(&path).unwrap_err();
    std::fs::remove_dir_all(&dir).unwrap();
    let msg = err.to_string();
    assert!(
        msg.contains("bad.pth") && msg.contains("os.system"),
        "{msg}"
    );
}

#[test]
fn corrupt_zip_data_fails_its_checksum() {
    let mut zip = read("oracle/fixtures/decoder_zip.pth");
    // Flip a byte inside the stored data of tensor `1.weight`.
    let sd = load_checkpoint_bytes(&zip).unwrap();
    let head = f32_bytes(&sd["1.weight"].data[..8]);
    let at = zip.windows(head.len()).position(|w| w == head).unwrap();
    zip[at + 5] ^= 0x40;
    assert!(matches!(
        load_checkpoint_bytes(&zip),
        Err(FormatError::Checksum { .. })
    ));
}

// ---------------------------------------------------------------------------------------------
// Fuzz-style robustness: truncations and byte flips give Ok or Err, never a panic.
// ---------------------------------------------------------------------------------------------

/// Offsets to try in a file of `len` bytes: all of the first and last `dense` bytes, and every
/// `step`-th byte in between.
fn offsets(len: usize, dense: usize, step: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (0..len.min(dense)).collect();
    v.extend((dense..len.saturating_sub(dense)).step_by(step));
    v.extend(len.saturating_sub(dense).max(dense)..len);
    v
}

#[test]
fn truncated_files_are_errors() {
    for (file, dense, step) in [
        (
            "weights/wct-relu1_1-3_1/feature_invertor_conv1_1.pth",
            usize::MAX,
            1,
        ),
        ("oracle/fixtures/decoder_legacy.pth", 6000, 997),
        ("oracle/fixtures/decoder_zip.pth", 6000, 997),
        ("oracle/fixtures/vgg_zip.pth", 2000, 9973),
    ] {
        let bytes = read(file);
        for cut in offsets(bytes.len(), dense, step) {
            let result = load_checkpoint_bytes(&bytes[..cut]);
            assert!(result.is_err(), "{file} cut at {cut} imported");
        }
    }
}

#[test]
fn flipped_bytes_never_panic() {
    // Legacy: every byte of a small real file, three ways. No checksum protects legacy files, so
    // a flip may import with different values; the test asserts only the absence of panics.
    let file = read("weights/wct-relu1_1-3_1/feature_invertor_conv1_1.pth");
    let mut errors = 0;
    for at in 0..file.len() {
        for mask in [0x01, 0x80, 0xff] {
            let mut bytes = file.clone();
            bytes[at] ^= mask;
            errors += usize::from(load_checkpoint_bytes(&bytes).is_err());
        }
    }
    assert!(errors > 0);

    // Zip: all metadata bytes (pickle, headers, central directory) and a sample of data bytes.
    // Every content byte is under a CRC-32, so a flip either fails or changes nothing we read.
    let file = read("oracle/fixtures/decoder_zip.pth");
    let original = load_checkpoint_bytes(&file).unwrap();
    let data_pkl_end = 0x40 + 3600; // the pickle of this fixture is 3.5 kB, after a 64-byte header
    let cd = file.len() - 4000; // its central directory and end records fit in 4 kB
    let mut sites: Vec<usize> = (0..data_pkl_end.min(file.len())).collect();
    sites.extend((data_pkl_end..cd).step_by(101));
    sites.extend(cd..file.len());
    for at in sites {
        let mut bytes = file.clone();
        bytes[at] ^= 0x5a;
        if let Ok(sd) = load_checkpoint_bytes(&bytes) {
            assert_eq!(
                sd, original,
                "flip at byte {at} changed the import silently"
            );
        }
    }
}
