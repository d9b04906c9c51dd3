//! The `acm-smooth` binary on a bundle written here: its result must equal the in-process
//! `bundle::smooth_bundle` on the same arrays, a bad file must fail without stopping others.

use acm_rs::camera::Camera;
use acm_rs::limits::StateMap;
use acm_rs::normalization::Normalization;
use acm_rs::npz::{read_npz, write_npz, Array};
use acm_rs::skeleton::Skeleton;
use acm_rs::tracking::bundle::{bundle_from_arrays, smooth_bundle};
use acm_rs::tracking::{Emission, SkeletonEmission};
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::process::Command;

fn arrays() -> BTreeMap<String, Array> {
    let parents = [-1i64, 0, 1, 1];
    let rest = [
        Vector3::new(0.0, 0.0, 0.0),
        Vector3::new(0.0, 0.0, 2.0),
        Vector3::new(1.0, 0.0, 3.0),
        Vector3::new(-1.0, 0.0, 3.0),
    ];
    let mr = [
        Vector3::new(0.0, 0.3, 0.0),
        Vector3::new(0.0, 0.3, 2.0),
        Vector3::new(1.1, 0.0, 3.1),
        Vector3::new(-1.1, 0.0, 3.1),
    ];
    let sk = Skeleton::from_rest_pose(&parents, &rest, vec![0, 1, 2, 3], &mr, &Vector3::y(), None)
        .unwrap();
    let cams: Vec<f64> = [0.0, 0.4, -0.4]
        .iter()
        .flat_map(|&a: &f64| {
            vec![
                0.0, a, 0.0, 0.0, 0.0, 25.0, 900.0, 900.0, 640.0, 512.0, -0.1, 0.0, 0.0, 0.0, 0.0,
            ]
        })
        .collect();
    let nb = sk.n_bones();
    let lim: Vec<f64> = (0..nb * 3)
        .flat_map(|_| [f64::NEG_INFINITY, f64::INFINITY])
        .collect();
    let norm = Normalization::default();
    let map = StateMap::new(
        nb,
        &vec![f64::NEG_INFINITY; 3 * nb],
        &vec![f64::INFINITY; 3 * nb],
        &norm,
        true,
    )
    .unwrap();
    let em = SkeletonEmission::new(
        sk.clone(),
        Camera::many_from_rows(&cams, 15).unwrap(),
        map,
        norm,
    )
    .unwrap();
    let (n, t_len, nm, nc) = (em.n_state(), 25, sk.n_markers(), 3);
    let mut z = vec![0.0; t_len * n];
    for t in 0..t_len {
        for i in 0..n {
            z[t * n + i] = 0.02 * ((t * (i + 3)) as f64 * 0.37).sin();
        }
    }
    let mut g = vec![0.0; t_len * em.n_meas()];
    em.eval_batch(&z, &mut g).unwrap();
    let mut det = vec![0.0; nc * t_len * nm * 2];
    for t in 0..t_len {
        for c in 0..nc {
            for k in 0..nm {
                for a in 0..2 {
                    let v = g[((t * nc + c) * nm + k) * 2 + a];
                    let noise = 0.5 * (((t * 31 + c * 7 + k * 3 + a) as f64) * 1.3).sin();
                    det[((c * t_len + t) * nm + k) * 2 + a] = (v + 1.0) * norm.pixel[a] + noise;
                }
            }
        }
    }
    det[10] = f64::NAN;
    det[11] = f64::NAN;
    let mut m = BTreeMap::new();
    let mut put = |k: &str, shape: Vec<usize>, d: Vec<f64>| {
        m.insert(k.to_string(), Array::new(shape, d).unwrap());
    };
    put(
        "parents",
        vec![4],
        parents.iter().map(|&p| p as f64).collect(),
    );
    put(
        "rest_frames",
        vec![nb, 3, 3],
        sk.rest_frames()
            .iter()
            .flat_map(|f| f.transpose().as_slice().to_vec())
            .collect(),
    );
    put("bone_lengths", vec![nb], sk.lengths().to_vec());
    put(
        "marker_joints",
        vec![nm],
        sk.marker_joints().iter().map(|&j| j as f64).collect(),
    );
    put(
        "marker_offsets",
        vec![nm, 3],
        sk.offsets().iter().flat_map(|v| [v.x, v.y, v.z]).collect(),
    );
    put("joint_limits", vec![nb, 3, 2], lim);
    put("cameras", vec![nc, 15], cams);
    put(
        "normalization",
        vec![4],
        vec![
            norm.translation,
            norm.rotation,
            norm.pixel[0],
            norm.pixel[1],
        ],
    );
    put("detections", vec![nc, t_len, nm, 2], det);
    put("mu0", vec![n], z[..n].to_vec());
    put("max_iter", vec![], vec![3.0]);
    m
}

#[test]
fn binary_matches_in_process_smoothing() {
    let dir = std::env::temp_dir().join(format!("acm-smooth-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let a = arrays();
    let input = dir.join("session.npz");
    write_npz(std::fs::File::create(&input).unwrap(), &a, &[]).unwrap();
    std::fs::write(dir.join("broken.npz"), b"garbage").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_acm-smooth"))
        .args(["-q", "--no-cov"])
        .arg(&input)
        .arg(dir.join("broken.npz"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("broken.npz"));
    // the result exists now: a second run refuses before any work unless --overwrite
    let again = Command::new(env!("CARGO_BIN_EXE_acm-smooth"))
        .args(["-q", "--no-cov"])
        .arg(&input)
        .output()
        .unwrap();
    assert_eq!(again.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&again.stderr).contains("pass --overwrite"));
    let res = read_npz(
        std::fs::File::open(dir.join("session.smoothed.npz")).unwrap(),
        "result",
    )
    .unwrap();
    assert!(!res.contains_key("state_cov"));
    let (expect, summary) =
        smooth_bundle(bundle_from_arrays(&a, "test").unwrap(), false, |_| true).unwrap();
    assert_eq!(summary.outcome.history.len(), 3);
    for key in ["joints", "joints_std", "state_mean", "Vx_diag", "status"] {
        assert_eq!(res[key].shape, expect[key].shape, "{key}");
        for (x, y) in res[key].data.iter().zip(&expect[key].data) {
            assert!(
                (x - y).abs() <= 1e-12 * (1.0 + y.abs()),
                "{key}: {x} vs {y}"
            );
        }
    }
    assert!(
        summary.mean_reprojection_px < 2.0,
        "{}",
        summary.mean_reprojection_px
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bundle_options_out_of_range_are_refused_by_name() {
    for (key, value, words) in [
        ("max_iter", 0.0, "whole number >= 1"),
        ("max_iter", 2.5, "whole number >= 1"),
        ("tol", -1.0, "> 0"),
        ("pcutoff", 90.0, "[0, 1]"),
        ("noise", 0.0, "> 0"),
        ("gate", -3.0, "NaN (off) or > 0"),
        ("ll_tol", -1e-3, "NaN (off) or > 0"),
    ] {
        let mut a = arrays();
        a.insert(
            key.to_string(),
            Array {
                shape: vec![],
                data: vec![value],
            },
        );
        if key == "pcutoff" {
            let (nc, t, nm) = (a["detections"].shape[0], a["detections"].shape[1], 4);
            a.insert(
                "likelihood".into(),
                Array {
                    shape: vec![nc, t, nm],
                    data: vec![1.0; nc * t * nm],
                },
            );
        }
        let err = match bundle_from_arrays(&a, "b.npz") {
            Ok(_) => panic!("{key} = {value} was accepted"),
            Err(e) => e.to_string(),
        };
        assert!(
            err.contains(key) && err.contains(words) && !err.contains("Some("),
            "{err}"
        );
    }
    // a wrong shape names the expected one without Rust's Option syntax
    let mut a = arrays();
    a.insert(
        "normalization".into(),
        Array {
            shape: vec![3],
            data: vec![1.0; 3],
        },
    );
    let err = bundle_from_arrays(&a, "b.npz").err().unwrap().to_string();
    assert!(
        err.contains("expected [4]") && !err.contains("Some("),
        "{err}"
    );
}
