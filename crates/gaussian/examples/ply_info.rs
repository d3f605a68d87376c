//! Prints what a 3DGS `.ply` holds: the Gaussian count, the SH degree, the feature width, the
//! bounding box of the means (all of them, and the 1st to 99th percentile per axis, which
//! ignores far-away floaters), the mean opacity and any extra vertex properties.
//!
//! ```text
//! cargo run --release -p dsgs-gaussian --example ply_info -- SCENE.ply [MORE.ply ...]
//! ```

use std::fmt::Write as _;
use std::path::Path;
use std::process::ExitCode;

use gaussian::ply::load_ply_with_extras;

const USAGE: &str = "usage: ply_info SCENE.ply [MORE.ply ...]\n\
    prints the Gaussian count, SH degree, feature width and bounding box of each file";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.iter().any(|a| a == "-h" || a == "--help") {
        println!("{USAGE}");
        return ExitCode::SUCCESS;
    }
    if args.is_empty() {
        eprintln!("{USAGE}");
        return ExitCode::FAILURE;
    }
    let mut status = ExitCode::SUCCESS;
    let mut first = true;
    for arg in &args {
        match info(Path::new(arg)) {
            Ok(text) => {
                if !first {
                    println!();
                }
                first = false;
                print!("{text}");
            }
            Err(e) => {
                eprintln!("error: {e}");
                status = ExitCode::FAILURE;
            }
        }
    }
    status
}

/// The report for one file.
fn info(path: &Path) -> Result<String, gaussian::PlyError> {
    let ply = load_ply_with_extras(path)?;
    let s = &ply.gaussians;
    let mut out = String::new();
    let mut line = |label: &str, value: String| {
        let _ = writeln!(out, "  {label:<16}{value}");
    };
    line("gaussians", s.len().to_string());
    line(
        "sh degree",
        format!(
            "{} ({} x 3 coefficients per Gaussian)",
            s.sh_degree,
            s.sh_coeffs_per_gaussian()
        ),
    );
    line("feature width", s.feature_dim.to_string());
    if let Some((lo, hi)) = s.bounds() {
        line("means min", fmt3(lo));
        line("means max", fmt3(hi));
        line(
            "means 1%",
            fmt3(std::array::from_fn(|a| quantile(s, a, 0.01))),
        );
        line(
            "means 99%",
            fmt3(std::array::from_fn(|a| quantile(s, a, 0.99))),
        );
        line(
            "extent",
            format!("{:.5} (half the box diagonal)", s.extent()),
        );
        let opacity = s.opacities().iter().map(|&o| o as f64).sum::<f64>() / s.len() as f64;
        line("mean opacity", format!("{opacity:.4}"));
    }
    if !ply.extras.is_empty() {
        let names: Vec<String> = ply
            .extras
            .iter()
            .map(|e| format!("{} ({})", e.name, e.ty.ply_name()))
            .collect();
        line("extra columns", names.join(", "));
    }
    Ok(format!("{}\n{out}", path.display()))
}

/// The `q`-quantile of coordinate `axis` of the means (nearest rank); the scene is not empty.
fn quantile(s: &gaussian::FeatureGaussians, axis: usize, q: f64) -> f32 {
    let mut v: Vec<f32> = s.means.iter().map(|m| m[axis]).collect();
    v.sort_by(f32::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

fn fmt3(v: [f32; 3]) -> String {
    format!("[{:>12.5}, {:>12.5}, {:>12.5}]", v[0], v[1], v[2])
}
