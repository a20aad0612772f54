//! Reading the checkpoints Python writes (`sync4d/runs/checkpoint.py`): one safetensors file
//! whose header metadata `"sync4d"` holds JSON (SH degree, near plane, background, D_theta's
//! hyperparameters, the motion model, the cameras of the run) and whose tensors hold the
//! canonical Gaussians (`gaussians.*`) and D_theta's weights (`deform.*`). A node checkpoint
//! (`"motion": "nodes"`, `sync4d/phase1/nodes.py`) also holds the control nodes (`nodes.*`) and
//! each Gaussian's nodes (`gaussians.node_index`); D_theta then moves the nodes and the
//! Gaussians follow them. Every problem is an error naming the file and what is wrong; nothing
//! here panics on bad bytes.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};
use serde_json::Value;

/// A checkpoint that could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {problem}")]
pub struct CheckpointError {
    /// The file.
    pub path: PathBuf,
    /// What is wrong with it.
    pub problem: String,
}

/// One camera of the run, as `camera_records` in Python stores it.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraRecord {
    /// "train" or "test".
    pub split: String,
    /// Image file name of the frame.
    pub name: String,
    /// Frame time in [0, 1].
    pub time: f64,
    /// World-to-camera 4x4, row-major, OpenCV axes.
    pub viewmat: [f64; 16],
    /// Focal lengths and principal point, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

/// One linear layer `y = W x + b`, `weight` row-major [out, in].
#[derive(Debug, Clone)]
pub struct Linear {
    /// Row-major [out, in].
    pub weight: Vec<f32>,
    /// [out].
    pub bias: Vec<f32>,
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
}

/// D_theta: ReLU trunk layers, then the 9-output head, and the output scales.
#[derive(Debug, Clone)]
pub struct DeformMlp {
    /// Hidden layers (each followed by ReLU).
    pub trunk: Vec<Linear>,
    /// Output layer: (dx, dw, dl), 9 values.
    pub head: Linear,
    /// Frequency bands L of the time encoding (1 + 2L values).
    pub bands: usize,
    /// The time encoding's lowest angular frequency (pi in checkpoints written before the
    /// setting existed).
    pub time_frequency: f32,
    /// Frequency bands of the position encoding (3 (1 + 2L) values; 0: the raw position).
    pub position_bands: usize,
    /// Output scales of dx, dw and dl.
    pub scales: [f32; 3],
    /// World units per unit of the position input: D_theta reads x0 / position_unit (1 in
    /// checkpoints written before the setting existed).
    pub position_unit: f32,
}

/// How a Gaussian blends the rigid motions of its nodes (`node_config.blend`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Blend {
    /// Linear blend skinning: the weighted mean of the nodes' transformed positions and of
    /// their quaternions.
    Linear,
    /// Dual-quaternion skinning: the weighted, normalised sum of the nodes' dual quaternions.
    DualQuaternion,
}

/// The control nodes of a node checkpoint (`"motion": "nodes"`): D_theta is evaluated on them,
/// and each Gaussian blends the rigid motions of its K nodes.
#[derive(Debug, Clone)]
pub struct Nodes {
    /// Number of nodes M.
    pub m: usize,
    /// Nodes per Gaussian K.
    pub k: usize,
    /// Canonical node positions p_j, M*3.
    pub positions: Vec<f32>,
    /// Inverse squared node radii 1 / r_j^2 = exp(-2 log_radii_j), at most 1e20 (as
    /// `sync4d.phase1.nodes` clamps them), M.
    pub inv_sq_radii: Vec<f32>,
    /// Node embeddings z_j (D_theta's latent input), M*E.
    pub embeddings: Vec<f32>,
    /// Each Gaussian's K nodes, N*K, each in 0..M.
    pub index: Vec<u32>,
    /// How a Gaussian blends its nodes' motions.
    pub blend: Blend,
}

/// Everything the renderer needs from a checkpoint.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    /// Number of Gaussians N.
    pub n: usize,
    /// Canonical means, N*3.
    pub means: Vec<f32>,
    /// Canonical quaternions (w, x, y, z; not necessarily unit), N*4.
    pub quats: Vec<f32>,
    /// Canonical log standard deviations, N*3.
    pub log_scales: Vec<f32>,
    /// Opacities in (0, 1) (the sigmoid of the stored logits), N.
    pub opacities: Vec<f32>,
    /// SH coefficients, N*K*3 (DC first), K = (sh_degree + 1)^2.
    pub sh: Vec<f32>,
    /// SH degree.
    pub sh_degree: u32,
    /// Per-Gaussian embeddings, N*E.
    pub embeddings: Vec<f32>,
    /// Embedding width E.
    pub embed_dim: usize,
    /// Static Gaussians, N (empty when the checkpoint marks none, and for node checkpoints):
    /// their canonical state is their state at every time; D_theta is not evaluated for them.
    pub is_static: Vec<bool>,
    /// The control nodes when the checkpoint's motion model is `"nodes"`; None: D_theta moves
    /// each Gaussian itself (`"gaussians"`, and checkpoints written before the setting).
    pub nodes: Option<Nodes>,
    /// The deformation MLP.
    pub mlp: DeformMlp,
    /// Near clipping plane of the run's renders, world units.
    pub near: f64,
    /// Background colour.
    pub background: [f32; 3],
    /// The run's cameras (empty when the checkpoint was written without them).
    pub cameras: Vec<CameraRecord>,
}

fn err(path: &Path, problem: impl Into<String>) -> CheckpointError {
    CheckpointError {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

/// Read and check the checkpoint at `path`.
pub fn read_checkpoint(path: &Path) -> Result<Checkpoint, CheckpointError> {
    let bytes = std::fs::read(path).map_err(|e| err(path, format!("cannot read ({e})")))?;
    parse_checkpoint(&bytes, path)
}

struct Tensors<'a> {
    st: SafeTensors<'a>,
    path: &'a Path,
}

impl Tensors<'_> {
    /// The bytes of tensor `name`, which must be of `dtype` (4-byte elements) and `shape`;
    /// `missing` ends the message for an absent tensor.
    fn bytes(
        &self,
        name: &str,
        dtype: Dtype,
        shape: &[usize],
        missing: &str,
    ) -> Result<&[u8], CheckpointError> {
        let t = self.st.tensor(name).map_err(|_| {
            err(
                self.path,
                format!(
                    "tensor '{name}' is missing (expected {dtype:?} of shape {shape:?}{missing})"
                ),
            )
        })?;
        if t.dtype() != dtype {
            return Err(err(
                self.path,
                format!("tensor '{name}' is {:?}, expected {dtype:?}", t.dtype()),
            ));
        }
        if t.shape() != shape {
            return Err(err(
                self.path,
                format!(
                    "tensor '{name}' has shape {:?}, expected {shape:?}",
                    t.shape()
                ),
            ));
        }
        let data = t.data();
        if data.len() != 4 * shape.iter().product::<usize>() {
            return Err(err(self.path, format!("tensor '{name}' is truncated")));
        }
        Ok(data)
    }

    /// The f32 tensor `name`, which must have `shape`; finite values only.
    fn get(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, CheckpointError> {
        let data = self.bytes(name, Dtype::F32, shape, "; not a sync4d checkpoint?")?;
        let v: Vec<f32> = data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(err(
                self.path,
                format!("tensor '{name}' holds NaN or inf (at flat index {i})"),
            ));
        }
        Ok(v)
    }

    /// The I32 tensor `name`, which must have `shape`, as indices each below `bound`.
    fn indices(
        &self,
        name: &str,
        shape: &[usize],
        bound: usize,
    ) -> Result<Vec<u32>, CheckpointError> {
        let data = self.bytes(name, Dtype::I32, shape, "")?;
        data.chunks_exact(4)
            .enumerate()
            .map(|(i, b)| {
                let v = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                match usize::try_from(v) {
                    Ok(u) if u < bound => Ok(u as u32),
                    _ => Err(err(
                        self.path,
                        format!(
                            "tensor '{name}' holds node index {v} (at flat index {i}), outside \
                             [0, {bound})"
                        ),
                    )),
                }
            })
            .collect()
    }

    /// The shape of tensor `name`.
    fn shape(&self, name: &str) -> Result<Vec<usize>, CheckpointError> {
        self.st
            .tensor(name)
            .map(|t| t.shape().to_vec())
            .map_err(|_| {
                err(
                    self.path,
                    format!("tensor '{name}' is missing (not a sync4d checkpoint?)"),
                )
            })
    }
}

fn num(meta: &Value, key: &str, path: &Path) -> Result<f64, CheckpointError> {
    meta.get(key)
        .and_then(Value::as_f64)
        .ok_or_else(|| err(path, format!("metadata lacks the number '{key}'")))
}

/// `deform_config.key`, a finite number > 0, or `default` when the checkpoint has none.
fn positive_or(dc: &Value, key: &str, default: f32, path: &Path) -> Result<f32, CheckpointError> {
    if dc.get(key).is_none() {
        return Ok(default);
    }
    let v = num(dc, key, path)?;
    if !(v.is_finite() && v > 0.0) {
        return Err(err(
            path,
            format!("deform_config.{key} must be finite and > 0, got {v}"),
        ));
    }
    Ok(v as f32)
}

fn camera_record(v: &Value, path: &Path) -> Result<CameraRecord, CheckpointError> {
    let bad = || err(path, format!("malformed camera record {v}"));
    let f = |k: &str| v.get(k).and_then(Value::as_f64).ok_or_else(bad);
    let vm: Vec<f64> = v
        .get("viewmat")
        .and_then(Value::as_array)
        .ok_or_else(bad)?
        .iter()
        .map(|x| x.as_f64().ok_or_else(bad))
        .collect::<Result<_, _>>()?;
    let viewmat: [f64; 16] = vm.try_into().map_err(|_| bad())?;
    let size = |k: &str| -> Result<u32, CheckpointError> {
        let s = f(k)?;
        if (1.0..=16384.0).contains(&s) && s.fract() == 0.0 {
            Ok(s as u32)
        } else {
            Err(bad())
        }
    };
    Ok(CameraRecord {
        split: v
            .get("split")
            .and_then(Value::as_str)
            .unwrap_or("")
            .to_string(),
        name: v
            .get("name")
            .and_then(Value::as_str)
            .unwrap_or("")
            .to_string(),
        time: f("time")?,
        viewmat,
        fx: f("fx")?,
        fy: f("fy")?,
        cx: f("cx")?,
        cy: f("cy")?,
        width: size("width")?,
        height: size("height")?,
    })
}

/// The error for a tensor a node checkpoint lacks: `expected` names its dtype and shape.
fn node_tensor_missing(t: &Tensors<'_>, name: &str, expected: &str) -> CheckpointError {
    err(
        t.path,
        format!("tensor '{name}' is missing (expected {expected}; \"motion\": \"nodes\" needs it)"),
    )
}

/// The shape of tensor `name` of a node checkpoint (`expected` for the error when missing).
fn node_shape(t: &Tensors<'_>, name: &str, expected: &str) -> Result<Vec<usize>, CheckpointError> {
    t.st.tensor(name)
        .map(|v| v.shape().to_vec())
        .map_err(|_| node_tensor_missing(t, name, expected))
}

/// The F32 tensor `name` of a node checkpoint, which must have `shape`.
fn node_f32(t: &Tensors<'_>, name: &str, shape: &[usize]) -> Result<Vec<f32>, CheckpointError> {
    node_shape(t, name, &format!("F32 of shape {shape:?}"))?;
    t.get(name, shape)
}

/// The `nodes.*` tensors and `gaussians.node_index` of a node checkpoint with `n` Gaussians.
fn read_nodes(
    t: &Tensors<'_>,
    n: usize,
    embed_dim: usize,
    blend: Blend,
) -> Result<Nodes, CheckpointError> {
    let pshape = node_shape(t, "nodes.positions", "F32 of shape [M, 3]")?;
    let m = pshape.first().copied().unwrap_or(0);
    if m == 0 && n > 0 {
        return Err(err(
            t.path,
            format!("tensor 'nodes.positions' has shape {pshape:?}, expected [M, 3] with M >= 1"),
        ));
    }
    let positions = node_f32(t, "nodes.positions", &[m, 3])?;
    let inv_sq_radii = node_f32(t, "nodes.log_radii", &[m])?
        .iter()
        .map(|v| (-2.0 * v).exp().min(1e20))
        .collect();
    let embeddings = node_f32(t, "nodes.embeddings", &[m, embed_dim])?;
    let name = "gaussians.node_index";
    let ishape = node_shape(t, name, &format!("I32 of shape [{n}, K]"))?;
    let k = if ishape.len() == 2 { ishape[1] } else { 0 };
    if ishape.len() != 2 || ishape[0] != n || k == 0 {
        return Err(err(
            t.path,
            format!("tensor '{name}' has shape {ishape:?}, expected [{n}, K] with K >= 1"),
        ));
    }
    let index = t.indices(name, &[n, k], m)?;
    Ok(Nodes {
        m,
        k,
        positions,
        inv_sq_radii,
        embeddings,
        index,
        blend,
    })
}

/// D_theta's hyperparameters (`deform_config` in the metadata).
struct DeformConfig {
    embed_dim: usize,
    bands: usize,
    hidden: usize,
    layers: usize,
    scales: [f32; 3],
    position_bands: usize,
    position_unit: f32,
    time_frequency: f32,
}

/// The safetensors header of `bytes` and its `"sync4d"` metadata, parsed as JSON.
fn read_header<'a>(
    bytes: &'a [u8],
    path: &'a Path,
) -> Result<(Value, Tensors<'a>), CheckpointError> {
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| err(path, format!("not a readable safetensors file ({e})")))?;
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| err(path, format!("not a readable safetensors file ({e})")))?;
    let empty = HashMap::new();
    let text = header
        .metadata()
        .as_ref()
        .unwrap_or(&empty)
        .get("sync4d")
        .ok_or_else(|| {
            err(
                path,
                "no 'sync4d' metadata: not a checkpoint written by sync4d",
            )
        })?;
    let meta: Value = serde_json::from_str(text)
        .map_err(|e| err(path, format!("'sync4d' metadata is not valid JSON ({e})")))?;
    Ok((meta, Tensors { st, path }))
}

/// The metadata's `sh_degree`, 0..=3.
fn sh_degree(meta: &Value, path: &Path) -> Result<u32, CheckpointError> {
    let sh_degree = num(meta, "sh_degree", path)?;
    if !(0.0..=3.0).contains(&sh_degree) || sh_degree.fract() != 0.0 {
        return Err(err(
            path,
            format!("sh_degree must be 0..=3, got {sh_degree}"),
        ));
    }
    Ok(sh_degree as u32)
}

/// The metadata's `deform_config`, checked.
fn deform_config(meta: &Value, path: &Path) -> Result<DeformConfig, CheckpointError> {
    let dc = meta
        .get("deform_config")
        .ok_or_else(|| err(path, "metadata lacks 'deform_config'"))?;
    let int = |k: &str| -> Result<usize, CheckpointError> {
        let v = num(dc, k, path)?;
        if (1.0..=4096.0).contains(&v) && v.fract() == 0.0 {
            Ok(v as usize)
        } else {
            Err(err(
                path,
                format!("deform_config.{k} must be a positive integer, got {v}"),
            ))
        }
    };
    let (embed_dim, bands, hidden, layers) = (
        int("embed_dim")?,
        int("bands")?,
        int("hidden")?,
        int("layers")?,
    );
    let scales = [
        num(dc, "scale_position", path)? as f32,
        num(dc, "scale_rotation", path)? as f32,
        num(dc, "scale_log_scale", path)? as f32,
    ];
    if bands > 30 {
        return Err(err(
            path,
            format!("deform_config.bands = {bands} is out of range"),
        ));
    }
    // Absent in checkpoints written before the option existed: the raw position.
    let position_bands = if dc.get("position_bands").is_none() {
        0
    } else {
        let v = num(dc, "position_bands", path)?;
        if !((0.0..=30.0).contains(&v) && v.fract() == 0.0) {
            return Err(err(
                path,
                format!("deform_config.position_bands must be an integer in 0..=30, got {v}"),
            ));
        }
        v as usize
    };
    // Absent in checkpoints written before each setting existed: the raw position, the
    // paper's pi.
    Ok(DeformConfig {
        embed_dim,
        bands,
        hidden,
        layers,
        scales,
        position_bands,
        position_unit: positive_or(dc, "position_unit", 1.0, path)?,
        time_frequency: positive_or(dc, "time_frequency", std::f32::consts::PI, path)?,
    })
}

/// How the Gaussians follow the nodes in a node checkpoint (`"motion": "nodes"`); None when
/// D_theta moves each Gaussian (`"gaussians"`, or no `motion`: checkpoints written before node
/// motion existed).
fn node_blend(meta: &Value, path: &Path) -> Result<Option<Blend>, CheckpointError> {
    let motion = match meta.get("motion") {
        None | Some(Value::Null) => "gaussians",
        Some(Value::String(s)) => s.as_str(),
        Some(other) => {
            return Err(err(
                path,
                format!("motion must be \"gaussians\" or \"nodes\", got {other}"),
            ))
        }
    };
    match motion {
        "gaussians" => Ok(None),
        "nodes" => {
            let nc = meta.get("node_config").ok_or_else(|| {
                err(
                    path,
                    "metadata lacks 'node_config' (\"motion\": \"nodes\" needs it)",
                )
            })?;
            match nc.get("blend").and_then(Value::as_str) {
                Some("linear") => Ok(Some(Blend::Linear)),
                Some("dual_quaternion") => Ok(Some(Blend::DualQuaternion)),
                _ => {
                    let got = nc
                        .get("blend")
                        .map_or("nothing".to_string(), Value::to_string);
                    Err(err(
                        path,
                        format!(
                            "node_config.blend must be \"linear\" or \"dual_quaternion\", got \
                             {got}"
                        ),
                    ))
                }
            }
        }
        other => Err(err(
            path,
            format!("motion must be \"gaussians\" or \"nodes\", got \"{other}\""),
        )),
    }
}

/// D_theta's weights (`deform.*`) for the hyperparameters `c`: the ReLU trunk, then the head.
fn read_mlp(t: &Tensors<'_>, c: &DeformConfig) -> Result<DeformMlp, CheckpointError> {
    let input = 3 * (1 + 2 * c.position_bands) + c.embed_dim + 1 + 2 * c.bands;
    let mut trunk = Vec::new();
    let mut width = input;
    for l in 0..c.layers - 1 {
        let name = format!("deform.trunk.{}", 2 * l);
        trunk.push(Linear {
            weight: t.get(&format!("{name}.weight"), &[c.hidden, width])?,
            bias: t.get(&format!("{name}.bias"), &[c.hidden])?,
            inputs: width,
            outputs: c.hidden,
        });
        width = c.hidden;
    }
    let head = Linear {
        weight: t.get("deform.head.weight", &[9, width])?,
        bias: t.get("deform.head.bias", &[9])?,
        inputs: width,
        outputs: 9,
    };
    Ok(DeformMlp {
        trunk,
        head,
        bands: c.bands,
        time_frequency: c.time_frequency,
        position_bands: c.position_bands,
        scales: c.scales,
        position_unit: c.position_unit,
    })
}

/// The metadata's near plane, background and the run's cameras (each optional).
fn view_settings(
    meta: &Value,
    path: &Path,
) -> Result<(f64, [f32; 3], Vec<CameraRecord>), CheckpointError> {
    let near = meta.get("near").and_then(Value::as_f64).unwrap_or(0.01);
    if !(near.is_finite() && near > 0.0) {
        return Err(err(
            path,
            format!("near must be finite and > 0, got {near}"),
        ));
    }
    let bg: Vec<f64> = meta
        .get("background")
        .and_then(Value::as_array)
        .map_or_else(
            || vec![1.0, 1.0, 1.0],
            |a| a.iter().filter_map(Value::as_f64).collect(),
        );
    if bg.len() != 3 || bg.iter().any(|v| !v.is_finite()) {
        return Err(err(path, "background must be 3 finite numbers"));
    }
    let cameras = match meta.get("run").and_then(|r| r.get("cameras")) {
        Some(Value::Array(list)) => list
            .iter()
            .map(|c| camera_record(c, path))
            .collect::<Result<_, _>>()?,
        _ => Vec::new(),
    };
    Ok((near, [bg[0] as f32, bg[1] as f32, bg[2] as f32], cameras))
}

/// Parse checkpoint `bytes` (errors name `path`): the metadata (SH degree, D_theta's
/// hyperparameters, the motion model), then the tensors it describes (the canonical Gaussians,
/// the nodes, D_theta's weights), then the view settings. One check per field of the format, in
/// the order they are read, so the first problem found is the one reported.
pub fn parse_checkpoint(bytes: &[u8], path: &Path) -> Result<Checkpoint, CheckpointError> {
    let (meta, t) = read_header(bytes, path)?;
    let sh_degree = sh_degree(&meta, path)?;
    let config = deform_config(&meta, path)?;
    let node_blend = node_blend(&meta, path)?;

    let n = *t.shape("gaussians.means")?.first().unwrap_or(&0);
    let k = ((sh_degree + 1) * (sh_degree + 1)) as usize;
    let means = t.get("gaussians.means", &[n, 3])?;
    let quats = t.get("gaussians.quats", &[n, 4])?;
    let log_scales = t.get("gaussians.log_scales", &[n, 3])?;
    let opacities: Vec<f32> = t
        .get("gaussians.opacity_logits", &[n])?
        .iter()
        .map(|x| 1.0 / (1.0 + (-x).exp()))
        .collect();
    let sh_dc = t.get("gaussians.sh_dc", &[n, 1, 3])?;
    let sh_rest = t.get("gaussians.sh_rest", &[n, k - 1, 3])?;
    let embed_dim = config.embed_dim;
    let embeddings = t.get("gaussians.embeddings", &[n, embed_dim])?;
    let nodes = match node_blend {
        None => None,
        Some(blend) => Some(read_nodes(&t, n, embed_dim, blend)?),
    };
    // Optional: written only when some Gaussian is static (sync4d.phase1.static); node
    // checkpoints have no static set (and one there is ignored).
    let is_static: Vec<bool> = if nodes.is_none() && t.st.tensor("gaussians.static").is_ok() {
        t.get("gaussians.static", &[n])?
            .iter()
            .map(|&v| v > 0.5)
            .collect()
    } else {
        Vec::new()
    };
    let mut sh = Vec::with_capacity(n * k * 3);
    for i in 0..n {
        sh.extend_from_slice(&sh_dc[3 * i..3 * i + 3]);
        sh.extend_from_slice(&sh_rest[3 * (k - 1) * i..3 * (k - 1) * (i + 1)]);
    }
    let mlp = read_mlp(&t, &config)?;
    let (near, background, cameras) = view_settings(&meta, path)?;
    Ok(Checkpoint {
        n,
        means,
        quats,
        log_scales,
        opacities,
        sh,
        sh_degree,
        embeddings,
        embed_dim,
        is_static,
        nodes,
        mlp,
        near,
        background,
        cameras,
    })
}
