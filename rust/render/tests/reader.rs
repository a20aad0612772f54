//! The checkpoint reader on a small checkpoint built here (the layout Python writes), and a
//! bounded fuzz: truncations and random byte corruptions must give an error or a checkpoint,
//! never a panic.

use std::collections::HashMap;
use std::path::Path;

use proptest::prelude::*;
use safetensors::{serialize, tensor::TensorView, Dtype};
use sync4d_render::checkpoint::parse_checkpoint;
use sync4d_render::deform::{deform_at, time_encoding};

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
    let input = 3 + E + 1 + 2 * BANDS;
    let mut specs: Vec<(String, Vec<usize>)> = vec![
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
    ];
    specs.sort();
    let data: Vec<Vec<u8>> = specs
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
            bytes_of(&v)
        })
        .collect();
    let views: Vec<(String, TensorView)> = specs
        .iter()
        .zip(&data)
        .map(|((name, shape), d)| {
            (
                name.clone(),
                TensorView::new(Dtype::F32, shape.clone(), d).unwrap(),
            )
        })
        .collect();
    let mut meta = serde_json::json!({
        "sh_degree": 1, "near": 0.05, "background": [1.0, 1.0, 1.0],
        "deform_config": {"embed_dim": E, "bands": BANDS, "hidden": HIDDEN, "layers": 2,
                          "scale_position": 0.1, "scale_rotation": 0.1, "scale_log_scale": 0.05},
        "run": {"cameras": [{"split": "test", "name": "r_0.png", "time": 0.5,
            "viewmat": [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 1.0],
            "fx": 20.0, "fy": 20.0, "cx": 8.0, "cy": 8.0, "width": 16, "height": 16}]}
    });
    for (k, v) in deform_extra.as_object().unwrap() {
        meta["deform_config"][k] = v.clone();
    }
    let info = HashMap::from([("sync4d".to_string(), meta.to_string())]);
    serialize(views, Some(info)).unwrap()
}

#[test]
fn reads_a_valid_checkpoint_and_deforms_it() {
    let ck = parse_checkpoint(&checkpoint(None), Path::new("ok.safetensors")).unwrap();
    assert_eq!(ck.n, N);
    assert_eq!(ck.sh.len(), N * 4 * 3);
    assert_eq!(ck.cameras.len(), 1);
    assert_eq!(ck.near, 0.05);
    let d = deform_at(&ck, 0.3);
    assert!(d
        .means
        .iter()
        .chain(&d.quats)
        .chain(&d.scales)
        .all(|v| v.is_finite()));
    for q in d.quats.chunks(4) {
        let n: f32 = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((n - 1.0).abs() < 1e-5);
    }
    assert_eq!(time_encoding(0.25, 2).len(), 5);
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
    ) {
        let mut b = checkpoint(None);
        for (pos, v) in flips {
            let i = pos % b.len();
            b[i] ^= v;
        }
        b.truncate(cut.min(b.len()));
        let _ = parse_checkpoint(&b, Path::new("fuzz.safetensors"));
    }
}
