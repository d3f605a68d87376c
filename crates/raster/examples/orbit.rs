//! Renders a 3DGS `.ply` from an orbit of cameras and writes one PNG per camera.
//!
//! ```text
//! cargo run --release -p dsgs-raster --example orbit -- SCENE.ply OUT_DIR [options]
//! ```
//!
//! The orbit circles the robust centre of the scene (the per-axis medians of the means) about
//! the `--up` axis, every camera looking at the centre. By default it starts at the world origin,
//! where 3DGS captures usually put their cameras, so the first frame looks at the scene from
//! where it was captured; with `--radius` (or when the origin lies too close to the centre) it
//! runs at that distance and at `--elevation` instead. The cameras come from
//! `gaussian::camera_path`, the renders from `raster::render` (SH colour at the file's degree).

use std::error::Error;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use gaussian::camera::MAX_IMAGE_SIDE;
use gaussian::camera_path::{look_at, orbit, orbit_from};
use gaussian::{load_ply, Camera, FeatureGaussians, Intrinsics};
use glam::DVec3;
use raster::{render, Channels, RenderOptions};

const USAGE: &str = "\
usage: orbit SCENE.ply OUT_DIR [options]
renders SCENE.ply from an orbit of cameras to OUT_DIR/frame_NNN.png

options:
  --frames N          number of cameras on the orbit (default 8)
  --size WxH          image size in pixels (default 320x240)
  --fov DEG           horizontal field of view in degrees (default 60)
  --up X,Y,Z          world up axis (default 0,-1,0, the COLMAP convention; 0,0,1 for NeRF scenes)
  --radius R          orbit radius in scene units (default: the distance from the centre to the
                      world origin, or twice the robust extent when the origin is near the centre)
  --elevation DEG     elevation above the plane orthogonal to up, with --radius (default 20)
  --background R,G,B  background colour in [0, 1] (default 0,0,0)";

/// The command line.
struct Args {
    scene: PathBuf,
    out_dir: PathBuf,
    frames: usize,
    width: u32,
    height: u32,
    fov_deg: f64,
    up: DVec3,
    radius: Option<f64>,
    elevation_deg: f64,
    background: [f32; 3],
}

fn main() -> ExitCode {
    let raw: Vec<String> = std::env::args().skip(1).collect();
    if raw.iter().any(|a| a == "-h" || a == "--help") {
        println!("{USAGE}");
        return ExitCode::SUCCESS;
    }
    let args = match parse_args(&raw) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("error: {e}\n\n{USAGE}");
            return ExitCode::from(2);
        }
    };
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn parse_args(raw: &[String]) -> Result<Args, String> {
    let mut positional = Vec::new();
    let mut args = Args {
        scene: PathBuf::new(),
        out_dir: PathBuf::new(),
        frames: 8,
        width: 320,
        height: 240,
        fov_deg: 60.0,
        up: DVec3::new(0.0, -1.0, 0.0),
        radius: None,
        elevation_deg: 20.0,
        background: [0.0; 3],
    };
    let mut it = raw.iter();
    while let Some(a) = it.next() {
        if !a.starts_with("--") {
            positional.push(a.clone());
            continue;
        }
        let value = it
            .next()
            .ok_or_else(|| format!("option {a} needs a value"))?;
        let bad = || format!("invalid value `{value}` for {a}");
        match a.as_str() {
            "--frames" => {
                args.frames = value.parse().map_err(|_| bad())?;
                if !(1..=100_000).contains(&args.frames) {
                    return Err(format!("--frames must lie in 1..=100000, got {value}"));
                }
            }
            "--size" => {
                let (w, h) = value.split_once(['x', 'X']).ok_or_else(bad)?;
                args.width = w.parse().map_err(|_| bad())?;
                args.height = h.parse().map_err(|_| bad())?;
                let side = 1..=MAX_IMAGE_SIDE;
                if !side.contains(&args.width) || !side.contains(&args.height) {
                    return Err(format!(
                        "--size must lie within 1x1 ..= {MAX_IMAGE_SIDE}x{MAX_IMAGE_SIDE}, got {value}"
                    ));
                }
            }
            "--fov" => {
                args.fov_deg = value.parse().map_err(|_| bad())?;
                if !(args.fov_deg > 0.0 && args.fov_deg < 180.0) {
                    return Err(format!(
                        "--fov must lie strictly between 0 and 180, got {value}"
                    ));
                }
            }
            "--up" => args.up = DVec3::from_array(floats::<3>(value).ok_or_else(bad)?),
            "--radius" => args.radius = Some(value.parse().map_err(|_| bad())?),
            "--elevation" => args.elevation_deg = value.parse().map_err(|_| bad())?,
            "--background" => {
                args.background = floats::<3>(value).ok_or_else(bad)?.map(|v| v as f32);
            }
            _ => return Err(format!("unknown option {a}")),
        }
    }
    match <[String; 2]>::try_from(positional) {
        Ok([scene, out_dir]) => {
            args.scene = scene.into();
            args.out_dir = out_dir.into();
            Ok(args)
        }
        Err(p) => Err(format!(
            "expected SCENE.ply and OUT_DIR, got {} positional argument(s)",
            p.len()
        )),
    }
}

/// `N` comma-separated finite numbers.
fn floats<const N: usize>(s: &str) -> Option<[f64; N]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse().ok())
        .collect::<Option<_>>()?;
    let a: [f64; N] = v.try_into().ok()?;
    a.iter().all(|x| x.is_finite()).then_some(a)
}

fn run(args: &Args) -> Result<(), Box<dyn Error>> {
    let scene = load_ply(&args.scene)?;
    if scene.is_empty() {
        return Err(format!("{} holds no Gaussians", args.scene.display()).into());
    }
    let cameras = orbit_cameras(&scene, args)?;
    let opts = RenderOptions::new(
        Channels::Color {
            sh_degree: scene.sh_degree,
        },
        args.background.to_vec(),
    );
    println!(
        "{}: {} Gaussians, SH degree {}; {} frames at {}x{}",
        args.scene.display(),
        scene.len(),
        scene.sh_degree,
        cameras.len(),
        args.width,
        args.height
    );
    std::fs::create_dir_all(&args.out_dir)
        .map_err(|e| format!("cannot create {}: {e}", args.out_dir.display()))?;
    for (f, camera) in cameras.iter().enumerate() {
        let start = Instant::now();
        let r = render(camera, &scene, &opts)?;
        let seconds = start.elapsed().as_secs_f64();
        let img = &r.raster;
        let path = args.out_dir.join(format!("frame_{f:03}.png"));
        write_png(&path, img.width, img.height, &img.image)?;
        let coverage = img.alpha.iter().map(|&a| a as f64).sum::<f64>() / img.alpha.len() as f64;
        let visible = r.projected.radii.iter().filter(|r| r[0] > 0).count();
        let c = camera.center();
        println!(
            "{}  eye ({:.2}, {:.2}, {:.2})  {visible} visible  coverage {:.1}%  {:.0} ms",
            path.display(),
            c.x,
            c.y,
            c.z,
            100.0 * coverage,
            1e3 * seconds
        );
    }
    Ok(())
}

/// The `q`-quantile of coordinate `axis` of the means (nearest rank).
fn quantile(s: &FeatureGaussians, axis: usize, q: f64) -> f64 {
    let mut v: Vec<f32> = s.means.iter().map(|m| m[axis]).collect();
    v.sort_by(f32::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize] as f64
}

/// The orbit described in the module documentation.
fn orbit_cameras(scene: &FeatureGaussians, args: &Args) -> Result<Vec<Camera>, Box<dyn Error>> {
    let center = DVec3::from_array(std::array::from_fn(|a| quantile(scene, a, 0.5)));
    let lo = DVec3::from_array(std::array::from_fn(|a| quantile(scene, a, 0.01)));
    let hi = DVec3::from_array(std::array::from_fn(|a| quantile(scene, a, 0.99)));
    let robust_extent = (0.5 * (hi - lo).length()).max(1e-6);
    let focal = 0.5 * args.width as f64 / (0.5 * args.fov_deg.to_radians()).tan();
    let intrinsics = Intrinsics {
        fx: focal,
        fy: focal,
        cx: 0.5 * args.width as f64,
        cy: 0.5 * args.height as f64,
        width: args.width,
        height: args.height,
    };
    let elevation = args.elevation_deg.to_radians();
    let circle = |radius: f64| orbit(intrinsics, center, radius, elevation, args.frames, args.up);
    if let Some(radius) = args.radius {
        return Ok(circle(radius)?);
    }
    // Start at the world origin unless it lies (nearly) on the orbit axis or at the centre.
    let to_origin = -center;
    let up = args.up.normalize_or_zero();
    let horizontal = to_origin - to_origin.dot(up) * up;
    if horizontal.length() > 0.25 * robust_extent {
        if let Some(start) = look_at(intrinsics, DVec3::ZERO, center, args.up) {
            return Ok(orbit_from(&start, center, args.frames, args.up)?);
        }
    }
    Ok(circle(2.0 * robust_extent)?)
}

/// Writes `height x width` RGB values in `[0, 1]` (clamped) as an 8-bit PNG.
fn write_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<(), Box<dyn Error>> {
    let bytes: Vec<u8> = rgb
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let img = image::RgbImage::from_raw(width, height, bytes).ok_or("image size mismatch")?;
    img.save(path)
        .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    Ok(())
}
