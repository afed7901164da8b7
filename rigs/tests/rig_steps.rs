//! Each normalisation step keeps the skinned mesh (and the world joint positions) identical
//! for every key time of every clip — on random rigs and on every rig in ../shared/testdata.
//! Re-orient and units give `R·v` and `s·v` of the original.
//!
//! `cargo test -p posecast-server --test rig_steps -- --nocapture` prints the figures.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::{Mat3, Mat4, Quat, Vec3};
use posecast_proto::testing::{arb_quat, f32s};
use posecast_rigs::rig::neutral::hanim_pose;
use posecast_rigs::rig::{
    RigError, SignedAxis, adjust_bind, apply_neutral_pose, map_names, reorient,
    reorient_bind_frame, scale_units, simplify,
};
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use rig_support::{all_rigs, arb_asset, deviation, snapshot};

/// Relative tolerance of the invariants (issue 4: 1e-4 × the model's height).
const TOL: f32 = 1e-4;

fn is_translation(m: &Mat4) -> bool {
    Mat3::from_mat4(*m) == Mat3::IDENTITY && m.row(3) == glam::Vec4::W
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn adjust_keeps_the_mesh(
        (asset, v) in arb_asset(1..30, false).prop_flat_map(|a| {
            let n = a.skeleton.len();
            (Just(a), prop::collection::vec(arb_quat(), n))
        })
    ) {
        let (after, maps, _) = adjust_bind(asset.clone(), &v).unwrap();
        let (dv, dj) = deviation(&asset, &after, |p| p);
        prop_assert!(dv <= TOL && dj <= TOL, "vertices {dv}, joints {dj}");
        // B'⁻¹ = V B⁻¹ and the maps are (V_parent, V⁻¹).
        for j in 0..v.len() {
            let expected = Mat4::from_quat(v[j]) * asset.skeleton.inverse_bind()[j];
            prop_assert!(after.skeleton.inverse_bind()[j].abs_diff_eq(expected, 1e-4));
            prop_assert!(maps[j].rot_post.dot(v[j].inverse()).abs() > 1.0 - 1e-6);
        }
        // Root translations are untouched.
        for r in asset.skeleton.roots() {
            prop_assert_eq!(after.skeleton.rest()[r].translation, asset.skeleton.rest()[r].translation);
        }
    }

    #[test]
    fn simplify_gives_translations_and_keeps_the_mesh(asset in arb_asset(1..30, false)) {
        let (after, _, _) = simplify(asset.clone()).unwrap();
        let (dv, dj) = deviation(&asset, &after, |p| p);
        prop_assert!(dv <= TOL && dj <= TOL, "vertices {dv}, joints {dj}");
        // Uniform joint scales make the binds scaled: the residual is a uniform stretch, and
        // the inverse bind's translation is −C_i scaled.
        for ib in after.skeleton.inverse_bind() {
            let l = Mat3::from_mat4(*ib);
            let s = l.x_axis.x;
            prop_assert!(l.abs_diff_eq(Mat3::from_diagonal(Vec3::splat(s)), 1e-4 * s.abs().max(1.0)));
        }
    }

    #[test]
    fn simplify_at_rest_gives_bone_vectors_and_identity_rest(asset in arb_asset(1..30, true)) {
        // Rigid rest == bind: B'⁻¹ = T(−C_i) exactly, t'_i = C_i − C_parent(i), rest rotations I.
        let rigid = rig_support::rigid(asset);
        let (after, _, _) = simplify(rigid.clone()).unwrap();
        let sk = &after.skeleton;
        let c: Vec<Vec3> = rigid.skeleton.bind_matrices().iter().map(|b| b.w_axis.truncate()).collect();
        for j in 0..sk.len() {
            prop_assert!(is_translation(&sk.inverse_bind()[j]), "joint {j}: {}", sk.inverse_bind()[j]);
            prop_assert!(sk.inverse_bind()[j].w_axis.truncate().abs_diff_eq(-c[j], 1e-4));
            let expected = c[j] - sk.parents()[j].map_or(Vec3::ZERO, |p| c[p]);
            prop_assert!(sk.rest()[j].translation.abs_diff_eq(expected, 1e-3), "joint {j}");
            prop_assert!(sk.rest()[j].rotation.dot(Quat::IDENTITY).abs() > 1.0 - 1e-5);
        }
        let (dv, _) = deviation(&rigid, &after, |p| p);
        prop_assert!(dv <= TOL);
    }

    #[test]
    fn reorient_gives_r_times_the_mesh(asset in arb_asset(1..30, false), r in arb_quat()) {
        let (after, _) = reorient(asset.clone(), r).unwrap();
        let (dv, dj) = deviation(&asset, &after, |p| r * p);
        prop_assert!(dv <= TOL && dj <= TOL, "vertices {dv}, joints {dj}");
        let (after, _) = reorient_bind_frame(asset.clone(), r).unwrap();
        let (dv, dj) = deviation(&asset, &after, |p| p);
        prop_assert!(dv <= TOL && dj <= TOL, "bind frame: vertices {dv}, joints {dj}");
        let bind_mesh = after.meshes[0].mesh.positions();
        for (a, b) in asset.meshes[0].mesh.positions().iter().zip(bind_mesh) {
            prop_assert!((r * *a).abs_diff_eq(*b, 1e-4));
        }
    }

    #[test]
    fn units_give_s_times_the_mesh(asset in arb_asset(1..30, false), s in f32s(0.001..100.0)) {
        let (after, _) = scale_units(asset.clone(), s).unwrap();
        let (dv, dj) = deviation(&asset, &after, |p| p * s);
        prop_assert!(dv <= TOL && dj <= TOL, "vertices {dv}, joints {dj}");
    }

    #[test]
    fn neutral_pose_reproduces_h_and_keeps_the_mesh(
        (asset, h) in arb_asset(1..30, false).prop_flat_map(|a| {
            let n = a.skeleton.len();
            (Just(a), prop::collection::vec(arb_quat(), n))
        })
    ) {
        let (after, _, _) = apply_neutral_pose(asset.clone(), &h).unwrap();
        let (dv, dj) = deviation(&asset, &after, |p| p);
        prop_assert!(dv <= TOL && dj <= TOL, "vertices {dv}, joints {dj}");
        // Identity rotations on the new rig == pose H on the old one.
        let mut posed = asset.skeleton.rest().to_vec();
        for (t, q) in posed.iter_mut().zip(&h) { t.rotation = *q; }
        let mut neutral = after.skeleton.rest().to_vec();
        for t in &mut neutral { t.rotation = Quat::IDENTITY; }
        let (a, _) = snapshot(&asset, &posed);
        let (b, _) = snapshot(&after, &neutral);
        let size = rig_support::model_size(&asset);
        for (x, y) in a.iter().zip(&b) {
            prop_assert!((*x - *y).length() <= TOL * size.max(1.0) * 10.0, "{x} vs {y}");
        }
    }
}

#[test]
fn mirrored_bind_is_reported() {
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let asset = arb_asset(3..4, true)
        .new_tree(&mut runner)
        .unwrap()
        .current();
    let mut ib = asset.skeleton.inverse_bind().to_vec();
    ib[1] = Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0)) * ib[1];
    let sk = &asset.skeleton;
    let mirrored = posecast_proto::Skeleton::new(
        sk.names().to_vec(),
        sk.parents().to_vec(),
        sk.rest().to_vec(),
        ib,
    )
    .unwrap();
    let asset = posecast_rigs::asset::Asset {
        skeleton: mirrored,
        ..asset
    };
    assert!(matches!(
        simplify(asset),
        Err(RigError::MirroredBind { joint: 1, .. })
    ));
}

#[test]
fn axes_give_the_expected_rotations() {
    use SignedAxis::*;
    let z_up = SignedAxis::rotation_to_y_up(PosZ, None).unwrap();
    assert!((z_up * Vec3::Z).abs_diff_eq(Vec3::Y, 1e-6));
    assert!((z_up * Vec3::NEG_Y).abs_diff_eq(Vec3::Z, 1e-6));
    let x_up = SignedAxis::rotation_to_y_up(PosX, None).unwrap();
    assert!((x_up * Vec3::X).abs_diff_eq(Vec3::Y, 1e-6));
    let back = SignedAxis::rotation_to_y_up(PosY, Some(NegZ)).unwrap();
    assert!((back * Vec3::NEG_Z).abs_diff_eq(Vec3::Z, 1e-6));
    assert!((back * Vec3::Y).abs_diff_eq(Vec3::Y, 1e-6));
    assert!(SignedAxis::rotation_to_y_up(PosY, Some(NegY)).is_err());
}

/// Every step on every shared rig, one after the other as the pipeline runs them.
#[test]
fn every_step_on_every_shared_rig() {
    println!(
        "{:<34} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "rig", "simplify", "reorient", "bindframe", "units", "neutral"
    );
    for asset in all_rigs() {
        let name = asset.name.clone();
        let (simple, _, _) = simplify(asset.clone()).unwrap_or_else(|e| panic!("{name}: {e}"));
        let d_simplify = deviation(&asset, &simple, |p| p);
        for ib in simple.skeleton.inverse_bind() {
            assert!(is_translation(ib), "{name}: {ib}");
        }
        let r = SignedAxis::rotation_to_y_up(SignedAxis::PosZ, None).unwrap();
        let (turned, _) = reorient(simple.clone(), r).unwrap();
        let d_reorient = deviation(&simple, &turned, |p| r * p);
        let (bound, _) = reorient_bind_frame(simple.clone(), r).unwrap();
        let d_bind = deviation(&simple, &bound, |p| p);
        let (scaled, _) = scale_units(bound.clone(), 0.01).unwrap();
        let d_units = deviation(&bound, &scaled, |p| p * 0.01);
        let names = map_names(&scaled.skeleton, None, &name).unwrap();
        let h = hanim_pose(&scaled, &names.hanim).unwrap_or_else(|_| {
            // Not humanoid: a fixed arbitrary pose still exercises the step.
            (0..scaled.skeleton.len())
                .map(|j| Quat::from_rotation_y(0.1 * j as f32) * Quat::from_rotation_x(0.3))
                .collect()
        });
        let (neutral, _, _) = apply_neutral_pose(scaled.clone(), &h).unwrap();
        let d_neutral = deviation(&scaled, &neutral, |p| p);
        let worst = |d: (f32, f32)| d.0.max(d.1);
        println!(
            "{name:<34} {:>10.2e} {:>10.2e} {:>10.2e} {:>10.2e} {:>10.2e}",
            worst(d_simplify),
            worst(d_reorient),
            worst(d_bind),
            worst(d_units),
            worst(d_neutral)
        );
        for (step, d) in [
            ("simplify", d_simplify),
            ("reorient", d_reorient),
            ("bind frame", d_bind),
            ("units", d_units),
            ("neutral", d_neutral),
        ] {
            assert!(d.0 <= TOL && d.1 <= TOL, "{name} {step}: {d:?}");
        }
    }
}
