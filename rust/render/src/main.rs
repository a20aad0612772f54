//! `sync4d-render`: render a sync4d checkpoint to PNGs without Python.
// Index loops mirror the maths (row/column indices) in the small fixed-size matrix code.
#![allow(clippy::needless_range_loop)]

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, ValueEnum};
use sync4d_gpu::{AdapterChoice, GpuDevice, GpuRasterState, GpuRasterizer};
use sync4d_raster::{Camera, RasterState};
use sync4d_render::checkpoint::{read_checkpoint, Blend, CameraRecord, Checkpoint};
use sync4d_render::deform::deform_at;
use sync4d_render::render::{render, Backend};

/// Render a sync4d checkpoint (written by `python -m sync4d fit`) to PNG images: one view at one
/// time, a time sweep, or an orbit around the scene. The deformation MLP is evaluated here, so
/// any time in [0, 1] can be rendered: per Gaussian, or for node checkpoints (motion "nodes")
/// per control node, each Gaussian blending its nodes' motions (linear or dual-quaternion, as
/// the checkpoint says). Cameras come from the run stored in the checkpoint.
#[derive(Parser, Debug)]
#[command(name = "sync4d-render", version, about, long_about = None)]
struct Args {
    /// Checkpoint file (RUN/checkpoint.safetensors) or a run folder containing one; per-Gaussian
    /// and node (motion "nodes") checkpoints of Phase 1 or 2 alike.
    checkpoint: PathBuf,
    /// Camera of the run: test:K, train:K, or a frame's image name (default test:0, else train:0).
    #[arg(long, value_name = "SPEC")]
    camera: Option<String>,
    /// Times in [0, 1] to render (default: the camera's own frame time). Several values write
    /// one PNG each into --out.
    #[arg(long, value_name = "T", num_args = 1..)]
    time: Vec<f64>,
    /// Render N times evenly spaced over [0, 1] from the camera (a time sweep).
    #[arg(long, value_name = "N")]
    sweep: Option<u32>,
    /// Render N views on a circle around the scene's centre (the point the run's cameras look
    /// at), rotating the camera about the world up axis, at --time (default 0).
    #[arg(long, value_name = "N")]
    orbit: Option<u32>,
    /// Output: a .png file for a single image, otherwise a folder (created) for frame_NNN.png.
    #[arg(long, value_name = "PATH", default_value = "render.png")]
    out: PathBuf,
    /// Rasterizer: cpu (sync4d-raster), wgpu (GPU, or lavapipe on CPUs), or auto (wgpu when a
    /// GPU adapter exists, else cpu).
    #[arg(long, value_enum, default_value_t = BackendArg::Cpu)]
    backend: BackendArg,
    /// CPU threads for the deformation MLP and the CPU rasterizer (default: all cores).
    #[arg(long, value_name = "N")]
    threads: Option<usize>,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum BackendArg {
    Cpu,
    Wgpu,
    Auto,
}

fn camera_of(rec: &CameraRecord) -> Result<Camera, String> {
    Camera::new(
        &rec.viewmat,
        rec.fx,
        rec.fy,
        rec.cx,
        rec.cy,
        rec.width,
        rec.height,
    )
    .map_err(|e| format!("camera {}: {e}", rec.name))
}

fn pick_camera<'a>(ck: &'a Checkpoint, spec: Option<&str>) -> Result<&'a CameraRecord, String> {
    if ck.cameras.is_empty() {
        return Err(
            "the checkpoint stores no cameras (write it with `python -m sync4d fit`)".into(),
        );
    }
    let of_split = |split: &str| -> Vec<&'a CameraRecord> {
        ck.cameras.iter().filter(|c| c.split == split).collect()
    };
    let spec = match spec {
        Some(s) => s.to_string(),
        None if !of_split("test").is_empty() => "test:0".into(),
        None => "train:0".into(),
    };
    if let Some((split, k)) = spec.split_once(':') {
        let k: usize = k
            .parse()
            .map_err(|_| format!("--camera {spec}: K must be a number"))?;
        let list = of_split(split);
        let count = list.len();
        return list.get(k).copied().ok_or_else(|| {
            format!("--camera {spec}: the run has {count} {split} cameras (0..{count})")
        });
    }
    ck.cameras
        .iter()
        .find(|c| {
            c.name == spec
                || Path::new(&c.name)
                    .file_stem()
                    .is_some_and(|s| s == spec.as_str())
        })
        .ok_or_else(|| format!("--camera {spec}: no camera with that name; use test:K or train:K"))
}

/// The point closest (least squares) to every camera's optical axis, and the mean up vector.
fn orbit_centre(ck: &Checkpoint) -> ([f64; 3], [f64; 3]) {
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    let mut up = [0.0f64; 3];
    for c in &ck.cameras {
        let v = &c.viewmat;
        let r = [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]];
        let t = [v[3], v[7], v[11]];
        let centre: Vec<f64> = (0..3)
            .map(|j| -(0..3).map(|i| r[i][j] * t[i]).sum::<f64>())
            .collect();
        let d = r[2];
        for i in 0..3 {
            for j in 0..3 {
                let p = f64::from(u8::from(i == j)) - d[i] * d[j];
                a[i][j] += p;
                b[i] += p * centre[j];
            }
            up[i] -= r[1][i];
        }
    }
    // Solve a x = b by Cramer's rule (a is symmetric positive semi-definite).
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&a);
    let mut x = [0.0; 3];
    if d.abs() > 1e-9 {
        for k in 0..3 {
            let mut m = a;
            for i in 0..3 {
                m[i][k] = b[i];
            }
            x[k] = det(&m) / d;
        }
    }
    let n = (up[0] * up[0] + up[1] * up[1] + up[2] * up[2])
        .sqrt()
        .max(1e-12);
    (x, [up[0] / n, up[1] / n, up[2] / n])
}

/// `rec` rotated by `angle` radians about the axis through `centre` along `up`.
fn orbit_view(rec: &CameraRecord, centre: [f64; 3], up: [f64; 3], angle: f64) -> CameraRecord {
    let (s, c) = angle.sin_cos();
    let [x, y, z] = up;
    let rot = [
        [
            c + x * x * (1.0 - c),
            x * y * (1.0 - c) - z * s,
            x * z * (1.0 - c) + y * s,
        ],
        [
            y * x * (1.0 - c) + z * s,
            c + y * y * (1.0 - c),
            y * z * (1.0 - c) - x * s,
        ],
        [
            z * x * (1.0 - c) - y * s,
            z * y * (1.0 - c) + x * s,
            c + z * z * (1.0 - c),
        ],
    ];
    // New world-to-camera: W' = W Q^T with Q the rotation about the centre, i.e.
    // R' = R rot^T and t' = t + R (centre - rot^T centre)... computed as W' p = W (Q^-1 p).
    let v = &rec.viewmat;
    let r = [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]];
    let t = [v[3], v[7], v[11]];
    let mut out = rec.clone();
    // Q^-1 p = rot^T (p - centre) + centre.
    let mut rq = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            rq[i][j] = (0..3).map(|k| r[i][k] * rot[j][k]).sum();
        }
    }
    let shift: Vec<f64> = (0..3)
        .map(|i| centre[i] - (0..3).map(|k| rot[k][i] * centre[k]).sum::<f64>())
        .collect();
    for i in 0..3 {
        for j in 0..3 {
            out.viewmat[4 * i + j] = rq[i][j];
        }
        out.viewmat[4 * i + 3] = t[i] + (0..3).map(|k| r[i][k] * shift[k]).sum::<f64>();
    }
    out
}

fn write_png(path: &Path, img: &[f32], width: u32, height: u32) -> Result<(), String> {
    let bytes: Vec<u8> = img
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    let file = std::fs::File::create(path)
        .map_err(|e| format!("{}: cannot write ({e})", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header()
        .and_then(|mut w| w.write_image_data(&bytes))
        .map_err(|e| format!("{}: cannot write PNG ({e})", path.display()))
}

fn backend(choice: BackendArg) -> Result<Backend, String> {
    let gpu = |c| {
        GpuDevice::new(c)
            .map(|d| Backend::Wgpu(Box::new(GpuRasterizer::new(d)), GpuRasterState::new()))
    };
    match choice {
        BackendArg::Cpu => Ok(Backend::Cpu(RasterState::new())),
        BackendArg::Wgpu => gpu(AdapterChoice::Auto).map_err(|e| e.to_string()),
        BackendArg::Auto => {
            Ok(gpu(AdapterChoice::Gpu).unwrap_or_else(|_| Backend::Cpu(RasterState::new())))
        }
    }
}

// The command, in order: threads, checkpoint, camera, backend, then one PNG per frame.
#[allow(clippy::too_many_lines)]
fn run(args: Args) -> Result<(), String> {
    if let Some(t) = args.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(t.max(1))
            .build_global()
            .map_err(|e| e.to_string())?;
    }
    let path = if args.checkpoint.is_dir() {
        args.checkpoint.join("checkpoint.safetensors")
    } else {
        args.checkpoint.clone()
    };
    let ck = read_checkpoint(&path).map_err(|e| e.to_string())?;
    let rec = pick_camera(&ck, args.camera.as_deref())?;
    for t in &args.time {
        if !(0.0..=1.0).contains(t) {
            return Err(format!("--time {t}: times must lie in [0, 1]"));
        }
    }
    // (camera, time) of every image to write.
    let mut jobs: Vec<(CameraRecord, f64)> = Vec::new();
    if let Some(n) = args.orbit {
        let (centre, up) = orbit_centre(&ck);
        let t = args.time.first().copied().unwrap_or(0.0);
        for k in 0..n.max(1) {
            let angle = std::f64::consts::TAU * f64::from(k) / f64::from(n.max(1));
            jobs.push((orbit_view(rec, centre, up, angle), t));
        }
    } else if let Some(n) = args.sweep {
        let n = n.max(1);
        for k in 0..n {
            jobs.push((
                rec.clone(),
                if n == 1 {
                    0.0
                } else {
                    f64::from(k) / f64::from(n - 1)
                },
            ));
        }
    } else if args.time.is_empty() {
        jobs.push((rec.clone(), rec.time));
    } else {
        jobs.extend(args.time.iter().map(|t| (rec.clone(), *t)));
    }
    let single = jobs.len() == 1 && args.out.extension().is_some_and(|e| e == "png");
    if !single {
        std::fs::create_dir_all(&args.out)
            .map_err(|e| format!("{}: cannot create folder ({e})", args.out.display()))?;
    }
    let mut be = backend(args.backend)?;
    let which = match &be {
        Backend::Cpu(_) => "cpu".to_string(),
        Backend::Wgpu(g, _) => format!("wgpu on {}", g.device().adapter),
    };
    let motion = match &ck.nodes {
        None => String::new(),
        Some(nodes) => format!(
            " moved by {} nodes ({} each, {} blend)",
            nodes.m,
            nodes.k,
            match nodes.blend {
                Blend::Linear => "linear",
                Blend::DualQuaternion => "dual-quaternion",
            }
        ),
    };
    eprintln!(
        "sync4d-render: {} Gaussians{motion}, camera {} ({}x{}), {} image(s), backend {which}",
        ck.n,
        rec.name,
        rec.width,
        rec.height,
        jobs.len()
    );
    let start = Instant::now();
    let mut first_frame = 0.0;
    for (k, (cam_rec, t)) in jobs.iter().enumerate() {
        let cam = camera_of(cam_rec)?;
        let g = deform_at(&ck, *t as f32);
        let img = render(&ck, &g, &cam, &mut be)?;
        let out = if single {
            args.out.clone()
        } else {
            args.out.join(format!("frame_{k:03}.png"))
        };
        write_png(&out, &img, cam.width, cam.height)?;
        if k == 0 {
            first_frame = start.elapsed().as_secs_f64();
        }
    }
    let secs = start.elapsed().as_secs_f64();
    // The first frame also builds the rasterizer's kernels (seconds on lavapipe): the rate
    // after it is what a longer render sustains.
    let after_first = if jobs.len() > 1 {
        format!(
            "; {:.2} frames per second after the first frame, which took {first_frame:.2} s",
            (jobs.len() - 1) as f64 / (secs - first_frame).max(1e-9)
        )
    } else {
        String::new()
    };
    eprintln!(
        "sync4d-render: wrote {} image(s) to {} in {secs:.2} s ({:.2} frames per second{after_first})",
        jobs.len(),
        args.out.display(),
        jobs.len() as f64 / secs.max(1e-9)
    );
    Ok(())
}

fn main() -> ExitCode {
    match run(Args::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sync4d-render: {e}");
            ExitCode::from(2)
        }
    }
}
