//! Image decoding is bounded: a file whose header claims a side above `MAX_IMAGE_SIDE`, or
//! pixels needing more than `MAX_DECODE_BYTES`, is refused with an error naming the file and
//! the limit, at once and without allocating for the claimed size. Ordinary images decode to
//! the same RGB `f32` values as the `image` crate's own conversion.
//!
//! This test binary counts the largest single allocation (a global allocator), so it holds no
//! other test that allocates much.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use dsgs_testkit::scratch_dir;
use gaussian::camera::{MAX_DECODE_BYTES, MAX_IMAGE_SIDE};
use gaussian::dataset::images::{image_size, load_rgb};
use gaussian::dataset::DatasetError;

/// The system allocator, recording the largest single request.
struct Largest;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Largest {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        System.alloc(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        System.alloc_zeroed(layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, Ordering::Relaxed);
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static ALLOCATOR: Largest = Largest;

/// CRC-32 (ISO-HDLC, as PNG chunks use), bit by bit.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_be_bytes());
}

/// A well-formed PNG of a few dozen bytes whose header claims `width x height` pixels of RGBA at
/// `bit_depth` bits (its pixel data is a token stored zlib block, far too short).
fn png_header_only(width: u32, height: u32, bit_depth: u8) -> Vec<u8> {
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[bit_depth, 6, 0, 0, 0]);
    chunk(&mut png, b"IHDR", &ihdr);
    chunk(
        &mut png,
        b"IDAT",
        &[0x78, 0x01, 0x01, 0x00, 0x00, 0xFF, 0xFF, 0, 0, 0, 1],
    );
    chunk(&mut png, b"IEND", &[]);
    png
}

/// Runs `f`, returning its result, how long it took and the largest single allocation made
/// meanwhile.
fn measured<T>(f: impl FnOnce() -> T) -> (T, Duration, usize) {
    LARGEST.store(0, Ordering::Relaxed);
    let t = Instant::now();
    let out = f();
    (out, t.elapsed(), LARGEST.load(Ordering::Relaxed))
}

/// Far below any decode of the claimed sizes (gigabytes), far above a header's buffers.
const SMALL: usize = 16 << 20;

fn too_large_message(result: Result<impl std::fmt::Debug, DatasetError>, file: &Path) -> String {
    match result {
        Err(e @ DatasetError::ImageTooLarge { .. }) => {
            let m = e.to_string();
            let name = file.file_name().unwrap().to_str().unwrap();
            assert!(m.contains(name), "names the file: {m}");
            m
        }
        other => panic!(
            "{}: expected an image-too-large error, got {other:?}",
            file.display()
        ),
    }
}

#[test]
fn oversized_headers_are_refused_at_once_without_allocating() {
    let dir = scratch_dir("limits", "huge");
    let side = MAX_IMAGE_SIDE.to_string();

    // A side above the limit: refused from the header, by both the size query and the decoder.
    // (The largest size PNG allows, 2^31 - 1 per side, is too large for the decoder even to
    // turn its header into a size; the error then names the memory limit beside the side one.)
    for (i, (w, h)) in [
        (MAX_IMAGE_SIDE + 1, 8),
        (8, 1_000_000),
        (i32::MAX as u32, i32::MAX as u32),
    ]
    .into_iter()
    .enumerate()
    {
        let file = dir.join(format!("huge{i}.png"));
        std::fs::write(&file, png_header_only(w, h, 8)).unwrap();
        for (what, (result, took, largest)) in [
            ("image_size", measured(|| image_size(&file).map(|_| ()))),
            (
                "load_rgb",
                measured(|| load_rgb(&file, [0.0; 3]).map(|_| ())),
            ),
        ] {
            let m = too_large_message(result, &file);
            println!("{what}: {m}");
            assert!(m.contains(&side), "{what} names the side limit: {m}");
            assert!(
                m.contains(&format!("{w}x{h}")) || m.contains(&MAX_DECODE_BYTES.to_string()),
                "{what} names the claimed size, or the memory limit it needs more than: {m}"
            );
            assert!(took < Duration::from_secs(2), "{what} took {took:?}");
            assert!(largest < SMALL, "{what} allocated {largest} bytes at once");
        }
    }

    // Within the side limit but more decoded bytes than allowed (16-bit RGBA at the largest
    // side): refused by the decoder before it allocates the pixels.
    let (w, h) = (MAX_IMAGE_SIDE, MAX_IMAGE_SIDE);
    assert!(w as u64 * h as u64 * 8 > MAX_DECODE_BYTES);
    let file = dir.join("deep.png");
    std::fs::write(&file, png_header_only(w, h, 16)).unwrap();
    assert_eq!(
        image_size(&file).unwrap(),
        (w, h),
        "the header alone is fine"
    );
    let (result, took, largest) = measured(|| load_rgb(&file, [0.0; 3]).map(|_| ()));
    let m = too_large_message(result, &file);
    assert!(
        m.contains(&MAX_DECODE_BYTES.to_string()),
        "names the memory limit: {m}"
    );
    assert!(took < Duration::from_secs(2), "took {took:?}");
    assert!(largest < SMALL, "allocated {largest} bytes at once");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Our one-pass conversion gives what `image`'s own float conversion and the documented
/// compositing (`rgb a + background (1 - a)`) give, for every pixel layout we decode.
#[test]
fn decoded_values_match_the_image_crate() {
    let dir = scratch_dir("limits", "layouts");
    let (w, h) = (7u32, 5u32);
    let code = |x: u32, y: u32, c: u32| ((x * 37 + y * 91 + c * 53) % 256) as u8;
    let wide = |x: u32, y: u32, c: u32| ((x * 9973 + y * 7919 + c * 4099) % 65536) as u16;
    let images: Vec<(&str, image::DynamicImage)> = vec![
        (
            "rgb8",
            image::RgbImage::from_fn(w, h, |x, y| image::Rgb([0, 1, 2].map(|c| code(x, y, c))))
                .into(),
        ),
        (
            "rgba8",
            image::RgbaImage::from_fn(w, h, |x, y| {
                image::Rgba([0, 1, 2, 3].map(|c| code(x, y, c)))
            })
            .into(),
        ),
        (
            "luma8",
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([code(x, y, 0)])).into(),
        ),
        (
            "lumaa8",
            image::GrayAlphaImage::from_fn(w, h, |x, y| {
                image::LumaA([code(x, y, 0), code(x, y, 3)])
            })
            .into(),
        ),
        (
            "rgb16",
            image::ImageBuffer::<image::Rgb<u16>, _>::from_fn(w, h, |x, y| {
                image::Rgb([0, 1, 2].map(|c| wide(x, y, c)))
            })
            .into(),
        ),
        (
            "rgba16",
            image::ImageBuffer::<image::Rgba<u16>, _>::from_fn(w, h, |x, y| {
                image::Rgba([0, 1, 2, 3].map(|c| wide(x, y, c)))
            })
            .into(),
        ),
    ];
    let background = [0.25f32, 0.5, 1.0];
    for (name, img) in images {
        let file = dir.join(format!("{name}.png"));
        img.save(&file).unwrap();
        let ours = load_rgb(&file, background).unwrap();
        assert_eq!((ours.width, ours.height), (w, h), "{name}");
        let reference = image::open(&file).unwrap().to_rgba32f();
        for (x, y, p) in reference.enumerate_pixels() {
            let a = p[3];
            let want: [f32; 3] = std::array::from_fn(|c| p[c] * a + background[c] * (1.0 - a));
            let got = ours.pixel(x, y);
            for c in 0..3 {
                assert!(
                    (got[c] - want[c]).abs() <= 1e-6,
                    "{name} ({x}, {y}) channel {c}: {got:?} vs {want:?}"
                );
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
