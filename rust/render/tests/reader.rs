//! The checkpoint reader on small checkpoints built here (the layout Python writes, with
//! per-Gaussian or node motion), and a bounded fuzz: truncations and random byte corruptions must give an error or a checkpoint,
//! never a panic.

use std::collections::HashMap;
use std::path::Path;

use proptest::prelude::*;
use safetensors::{serialize, tensor::TensorView, Dtype};
use sync4d_render::checkpoint::{parse_checkpoint, Blend};
use sync4d_render::deform::{deform_at, time_encoding, Deformed};

/// Whether every deformed mean, quaternion and scale is finite.
fn all_finite(d: &Deformed) -> bool {
    d.means
        .iter()
        .chain(&d.quats)
        .chain(&d.scales)
        .all(|v| v.is_finite())
}

const N: usize = 5;
const E: usize = 4;
const BANDS: usize = 2;
const HIDDEN: usize = 6;

fn bytes_of(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// A valid checkpoint: N Gaussians, SH degree 1, a 2-layer D_theta; `poison` puts a NaN into
/// the named tensor.
fn checkpoint(poison: Option<&str>) -> Vec<u8> {
    checkpoint_with(poison, serde_json::json!({}))
}

/// `checkpoint`, with the keys of `deform_extra` set in its `deform_config`.
fn checkpoint_with(poison: Option<&str>, deform_extra: serde_json::Value) -> Vec<u8> {
    let mut meta = meta();
    for (k, v) in deform_extra.as_object().unwrap() {
        meta["deform_config"][k] = v.clone();
    }
    build(base_specs(), Vec::new(), poison, &meta)
}

/// The tensors (names and shapes) of a per-Gaussian checkpoint.
fn base_specs() -> Vec<(String, Vec<usize>)> {
    let input = 3 + E + 1 + 2 * BANDS;
    vec![
        ("gaussians.means".into(), vec![N, 3]),
        ("gaussians.quats".into(), vec![N, 4]),
        ("gaussians.log_scales".into(), vec![N, 3]),
        ("gaussians.opacity_logits".into(), vec![N]),
        ("gaussians.sh_dc".into(), vec![N, 1, 3]),
        ("gaussians.sh_rest".into(), vec![N, 3, 3]),
        ("gaussians.embeddings".into(), vec![N, E]),
        ("deform.trunk.0.weight".into(), vec![HIDDEN, input]),
        ("deform.trunk.0.bias".into(), vec![HIDDEN]),
        ("deform.head.weight".into(), vec![9, HIDDEN]),
        ("deform.head.bias".into(), vec![9]),
    ]
}

/// The header of a per-Gaussian checkpoint.
fn meta() -> serde_json::Value {
    serde_json::json!({
        "sh_degree": 1, "near": 0.05, "background": [1.0, 1.0, 1.0],
        "deform_config": {"embed_dim": E, "bands": BANDS, "hidden": HIDDEN, "layers": 2,
                          "scale_position": 0.1, "scale_rotation": 0.1, "scale_log_scale": 0.05},
        "run": {"cameras": [{"split": "test", "name": "r_0.png", "time": 0.5,
            "viewmat": [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 1.0],
            "fx": 20.0, "fy": 20.0, "cx": 8.0, "cy": 8.0, "width": 16, "height": 16}]}
    })
}

/// A safetensors file of F32 tensors `specs` (deterministic values; `poison` puts a NaN into
/// the named one), I32 tensors `ints` and header `meta`.
fn build(
    mut specs: Vec<(String, Vec<usize>)>,
    ints: Vec<(String, Vec<usize>, Vec<i32>)>,
    poison: Option<&str>,
    meta: &serde_json::Value,
) -> Vec<u8> {
    specs.sort();
    let mut data: Vec<(String, Vec<usize>, Dtype, Vec<u8>)> = specs
        .iter()
        .enumerate()
        .map(|(k, (name, shape))| {
            let len: usize = shape.iter().product();
            let mut v: Vec<f32> = (0..len)
                .map(|i| ((i * 7 + k * 3) % 11) as f32 * 0.05 - 0.2)
                .collect();
            if name == "gaussians.quats" {
                v = (0..len)
                    .map(|i| if i % 4 == 0 { 1.0 } else { 0.1 })
                    .collect();
            }
            if poison == Some(name.as_str()) {
                v[0] = f32::NAN;
            }
            (name.clone(), shape.clone(), Dtype::F32, bytes_of(&v))
        })
        .collect();
    for (name, shape, v) in ints {
        let bytes = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        data.push((name, shape, Dtype::I32, bytes));
    }
    let views: Vec<(String, TensorView<'_>)> = data
        .iter()
        .map(|(name, shape, dtype, d)| {
            (
                name.clone(),
                TensorView::new(*dtype, shape.clone(), d).unwrap(),
            )
        })
        .collect();
    let info = HashMap::from([("sync4d".to_string(), meta.to_string())]);
    serialize(views, Some(info)).unwrap()
}

const M: usize = 3;
const K: usize = 2;

/// A node checkpoint (M nodes, K per Gaussian, `blend`), with `edit` applied to its tensors
/// (F32 names and shapes, the I32 node index) and header first.
fn node_checkpoint(
    blend: &str,
    edit: impl FnOnce(
        &mut Vec<(String, Vec<usize>)>,
        &mut Vec<(String, Vec<usize>, Vec<i32>)>,
        &mut serde_json::Value,
    ),
) -> Vec<u8> {
    let mut specs = base_specs();
    specs.push(("nodes.positions".into(), vec![M, 3]));
    specs.push(("nodes.log_radii".into(), vec![M]));
    specs.push(("nodes.embeddings".into(), vec![M, E]));
    let index: Vec<i32> = (0..N * K).map(|i| (i % M) as i32).collect();
    let mut ints = vec![("gaussians.node_index".to_string(), vec![N, K], index)];
    let mut meta = meta();
    meta["motion"] = "nodes".into();
    meta["node_config"] = serde_json::json!({ "count": M, "neighbours": K, "blend": blend });
    edit(&mut specs, &mut ints, &mut meta);
    build(specs, ints, None, &meta)
}

fn error_of(bytes: &[u8]) -> String {
    parse_checkpoint(bytes, Path::new("nodes.safetensors"))
        .unwrap_err()
        .to_string()
}

#[test]
fn reads_a_valid_checkpoint_and_deforms_it() {
    let ck = parse_checkpoint(&checkpoint(None), Path::new("ok.safetensors")).unwrap();
    assert_eq!(ck.n, N);
    assert_eq!(ck.sh.len(), N * 4 * 3);
    assert_eq!(ck.cameras.len(), 1);
    assert_eq!(ck.near, 0.05);
    let d = deform_at(&ck, 0.3);
    assert!(all_finite(&d));
    for q in d.quats.chunks(4) {
        let n: f32 = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((n - 1.0).abs() < 1e-5);
    }
    assert_eq!(time_encoding(0.25, 2, std::f32::consts::PI).len(), 5);
}

#[test]
fn bad_tensors_are_named() {
    let msg = parse_checkpoint(
        &checkpoint(Some("gaussians.quats")),
        Path::new("nan.safetensors"),
    )
    .unwrap_err()
    .to_string();
    assert!(
        msg.contains("nan.safetensors") && msg.contains("gaussians.quats") && msg.contains("NaN"),
        "{msg}"
    );
    let msg = parse_checkpoint(b"not a checkpoint", Path::new("x"))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("safetensors"), "{msg}");
}

#[test]
fn bad_position_bands_are_refused_by_name() {
    for bad in [
        serde_json::json!(2.5),
        serde_json::json!(-1),
        serde_json::json!(31),
    ] {
        let bytes = checkpoint_with(None, serde_json::json!({ "position_bands": bad }));
        let msg = parse_checkpoint(&bytes, Path::new("pb.safetensors"))
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains("pb.safetensors") && msg.contains("position_bands"),
            "{msg}"
        );
    }
    // A valid count whose first layer was trained for the raw position: a shape error.
    let bytes = checkpoint_with(None, serde_json::json!({ "position_bands": 1 }));
    let msg = parse_checkpoint(&bytes, Path::new("pb.safetensors"))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("deform.trunk.0.weight"), "{msg}");
    let ok = checkpoint_with(None, serde_json::json!({ "position_bands": 0 }));
    assert!(parse_checkpoint(&ok, Path::new("pb.safetensors")).is_ok());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn truncated_or_corrupted_bytes_never_panic(
        cut in 0usize..4000,
        flips in proptest::collection::vec((0usize..4000, any::<u8>()), 0..6),
        nodes in any::<bool>(),
    ) {
        let mut b = if nodes {
            node_checkpoint("dual_quaternion", |_, _, _| {})
        } else {
            checkpoint(None)
        };
        for (pos, v) in flips {
            let i = pos % b.len();
            b[i] ^= v;
        }
        b.truncate(cut.min(b.len()));
        let _ = parse_checkpoint(&b, Path::new("fuzz.safetensors"));
    }
}

#[test]
fn reads_node_checkpoints_and_deforms_them() {
    for (blend, want) in [
        ("linear", Blend::Linear),
        ("dual_quaternion", Blend::DualQuaternion),
    ] {
        let ck = parse_checkpoint(&node_checkpoint(blend, |_, _, _| {}), Path::new("n")).unwrap();
        let nodes = ck.nodes.as_ref().expect("a node checkpoint");
        assert_eq!((nodes.m, nodes.k, nodes.blend), (M, K, want));
        assert_eq!(nodes.index.len(), N * K);
        assert!(nodes.inv_sq_radii.iter().all(|r| *r > 0.0 && r.is_finite()));
        let d = deform_at(&ck, 0.3);
        assert!(all_finite(&d));
    }
    // A static set in a node checkpoint is ignored; "motion": "gaussians" is today's model.
    let ck = parse_checkpoint(
        &node_checkpoint("linear", |specs, _, _| {
            specs.push(("gaussians.static".into(), vec![N]));
        }),
        Path::new("n"),
    )
    .unwrap();
    assert!(ck.is_static.is_empty());
    let mut m = meta();
    m["motion"] = "gaussians".into();
    let ck = parse_checkpoint(&build(base_specs(), Vec::new(), None, &m), Path::new("g")).unwrap();
    assert!(ck.nodes.is_none());
    let old = parse_checkpoint(&checkpoint(None), Path::new("old")).unwrap();
    assert!(old.nodes.is_none());
}

#[test]
fn bad_node_checkpoints_are_refused_by_name() {
    // Missing tensors, named with the file and the shape they need.
    for name in ["nodes.positions", "nodes.log_radii", "nodes.embeddings"] {
        let msg = error_of(&node_checkpoint("linear", |specs, _, _| {
            specs.retain(|(n, _)| n != name);
        }));
        assert!(
            msg.contains("nodes.safetensors") && msg.contains(name) && msg.contains("missing"),
            "{msg}"
        );
    }
    let msg = error_of(&node_checkpoint("linear", |specs, _, _| {
        specs.retain(|(n, _)| n != "nodes.log_radii");
    }));
    assert!(msg.contains(&format!("[{M}]")), "{msg}");
    let msg = error_of(&node_checkpoint("linear", |_, ints, _| ints.clear()));
    assert!(
        msg.contains("gaussians.node_index") && msg.contains(&format!("[{N}, K]")),
        "{msg}"
    );
    // Wrong shapes.
    let msg = error_of(&node_checkpoint("linear", |specs, _, _| {
        specs.retain(|(n, _)| n != "nodes.embeddings");
        specs.push(("nodes.embeddings".into(), vec![M, E + 1]));
    }));
    assert!(
        msg.contains("nodes.embeddings") && msg.contains(&format!("expected [{M}, {E}]")),
        "{msg}"
    );
    let msg = error_of(&node_checkpoint("linear", |specs, _, _| {
        specs.retain(|(n, _)| n != "nodes.log_radii");
        specs.push(("nodes.log_radii".into(), vec![M, 1]));
    }));
    assert!(
        msg.contains("nodes.log_radii") && msg.contains(&format!("expected [{M}]")),
        "{msg}"
    );
    for shape in [vec![N + 1, K], vec![N * K], vec![N, 0]] {
        let msg = error_of(&node_checkpoint("linear", move |_, ints, _| {
            let len = shape.iter().product();
            ints[0] = ("gaussians.node_index".into(), shape, vec![0; len]);
        }));
        assert!(
            msg.contains("gaussians.node_index") && msg.contains("expected"),
            "{msg}"
        );
    }
    // The node index as F32, or out of range.
    let msg = error_of(&node_checkpoint("linear", |specs, ints, _| {
        ints.clear();
        specs.push(("gaussians.node_index".into(), vec![N, K]));
    }));
    assert!(
        msg.contains("gaussians.node_index") && msg.contains("I32"),
        "{msg}"
    );
    for bad in [M as i32, -1] {
        let msg = error_of(&node_checkpoint("linear", |_, ints, _| {
            ints[0].2[3] = bad;
        }));
        assert!(
            msg.contains("gaussians.node_index")
                && msg.contains(&bad.to_string())
                && msg.contains(&format!("[0, {M})")),
            "{msg}"
        );
    }
    // Unknown settings.
    let msg = error_of(&node_checkpoint("slerp", |_, _, _| {}));
    assert!(
        msg.contains("node_config.blend") && msg.contains("slerp"),
        "{msg}"
    );
    let msg = error_of(&node_checkpoint("linear", |_, _, meta| {
        meta["motion"] = "bones".into();
    }));
    assert!(msg.contains("motion") && msg.contains("bones"), "{msg}");
    let msg = error_of(&node_checkpoint("linear", |_, _, meta| {
        meta.as_object_mut().unwrap().remove("node_config");
    }));
    assert!(msg.contains("node_config"), "{msg}");
}

#[test]
fn position_unit_scales_the_position_input() {
    let plain = parse_checkpoint(&checkpoint(None), Path::new("u")).unwrap();
    assert_eq!(plain.mlp.position_unit, 1.0);
    let bytes = checkpoint_with(None, serde_json::json!({ "position_unit": 2.0 }));
    let ck = parse_checkpoint(&bytes, Path::new("u")).unwrap();
    assert_eq!(ck.mlp.position_unit, 2.0);
    assert_ne!(deform_at(&ck, 0.4).means, deform_at(&plain, 0.4).means);
    for bad in [serde_json::json!(0.0), serde_json::json!(-1.0)] {
        let bytes = checkpoint_with(None, serde_json::json!({ "position_unit": bad }));
        let msg = parse_checkpoint(&bytes, Path::new("u.safetensors"))
            .unwrap_err()
            .to_string();
        assert!(msg.contains("position_unit"), "{msg}");
    }
}
