//! CSE169 importers on the course files in ../shared/testdata/cse169: counts from SOURCES.md,
//! DOF limit clamping, bind-pose skinning and hand-computed Hermite values of `wasp_walk.anim`.

#![allow(clippy::unwrap_used)]
use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_proto::testing::require_testdata;
use posecast_rigs::clip::RotationChannel;
use posecast_rigs::import::{self, anim, cse169, skel, skin};

fn text(rel: &str) -> Option<String> {
    let path = require_testdata(rel)?;
    Some(std::fs::read_to_string(path).unwrap())
}

#[test]
fn test_skel_clamps_knee_r_pose() {
    let Some(t) = text("cse169/test.skel") else {
        return;
    };
    let s = skel::parse("test.skel", &t).unwrap();
    assert_eq!(
        s.skeleton.names(),
        &["root", "head", "hip_l", "knee_l", "hip_r", "knee_r"]
    );
    let knee = s.skeleton.find("knee_r").unwrap();
    let d = s.skeleton.dofs()[knee].dofs();
    assert_eq!((d[0].value, d[1].value, d[2].value), (-2.0, 0.0, 0.0));
    assert_eq!((d[0].min, d[0].max), (-2.0, 0.0));
    // Rest rotation = R_x(−2); rest translation = offset.
    let rest = s.skeleton.rest()[knee];
    assert!(rest.rotation.dot(Quat::from_rotation_x(-2.0)).abs() > 1.0 - 1e-6);
    assert_eq!(rest.translation, Vec3::new(0.0, -0.3, 0.0));
    // Root pose 0 0.1 0 is within its (free) limits.
    assert!(
        s.skeleton.rest()[0]
            .rotation
            .dot(Quat::from_rotation_y(0.1))
            .abs()
            > 1.0 - 1e-6
    );
    assert_eq!(
        s.boxes[0],
        (Vec3::new(-0.2, -0.3, -0.15), Vec3::new(0.2, 0.3, 0.15))
    );
}

#[test]
fn tube_skel_and_skin() {
    let (Some(k), Some(m)) = (text("cse169/tube.skel"), text("cse169/tube_smooth.skin")) else {
        return;
    };
    let s = skel::parse("tube.skel", &k).unwrap();
    assert_eq!(s.skeleton.len(), 2);
    assert_eq!(
        s.offsets,
        vec![Vec3::new(0.0, 0.5, 0.0), Vec3::new(0.0, -0.5, 0.0)]
    );
    assert!(
        s.skeleton.rest()[1]
            .rotation
            .dot(Quat::from_rotation_z(1.0))
            .abs()
            > 1.0 - 1e-6
    );
    let skin = skin::parse("tube_smooth.skin", &m, &s.skeleton).unwrap();
    assert_eq!(skin.mesh.vertex_count(), 240);
    assert_eq!(skin.mesh.indices().len(), 456 * 3);
    assert_eq!(skin.bind.len(), 2);
    assert_eq!(skin.mesh.influences(), 2);
    // B puts the shoulder at the origin while the .skel puts it at (0, 0.5, 0).
    assert_eq!(skin.bind[0].w_axis.truncate(), Vec3::ZERO);
    let asset = cse169::assemble("tube", s, Some(skin), vec![]).unwrap();
    assert_eq!(asset.meshes.len(), 1);
}

#[test]
fn triangle_skin_with_one_joint() {
    let Some(m) = text("cse169/triangle.skin") else {
        return;
    };
    let s = skel::parse("one.skel", "balljoint only { }").unwrap();
    let skin = skin::parse("triangle.skin", &m, &s.skeleton).unwrap();
    assert_eq!(skin.mesh.vertex_count(), 3);
    assert_eq!(skin.mesh.indices(), &[0, 1, 2]);
    assert_eq!(skin.bind, vec![Mat4::IDENTITY]);
    let n = Vec3::new(-1.0, -1.0, 1.0).normalize();
    assert!(
        skin.mesh.normals()[0].abs_diff_eq(n, 1e-6)
            || skin.mesh.normals()[0] == Vec3::new(-1.0, -1.0, 1.0)
    );
}

#[test]
fn wasp_loads_and_zero_pose_skins_to_bind() {
    let Some(path) = require_testdata("cse169/wasp.skel") else {
        return;
    };
    let assets = import::load_path(&path).unwrap();
    assert_eq!(assets.len(), 1);
    let a = &assets[0];
    assert_eq!(a.skeleton.len(), 23);
    assert_eq!(a.meshes.len(), 1);
    let mesh = &a.meshes[0].mesh;
    assert_eq!(mesh.vertex_count(), 694);
    assert_eq!(mesh.indices().len(), 1236 * 3);
    assert_eq!(mesh.influences(), 4);
    // wasp.skel has no boxes: every joint gets the default.
    assert!(
        a.boxes
            .as_ref()
            .unwrap()
            .iter()
            .all(|b| *b == skel::DEFAULT_BOX)
    );
    // The .anim next to it is picked up by stem prefix.
    assert_eq!(a.clips.len(), 1);
    assert_eq!(a.clips[0].name(), "wasp_walk");
    assert_eq!((a.clips[0].start(), a.clips[0].end()), (0.0, 4.0));

    // Zero pose: all rotations zero, the root placed where the bindings put it (SOURCES.md:
    // (0, 0.95, −0.15)). Then W_j = B_j for every joint, and skinning is the identity.
    let binds = a.skeleton.bind_matrices();
    let root_t = binds[0].w_axis.truncate();
    assert!(root_t.abs_diff_eq(Vec3::new(0.0, 0.95, -0.15), 1e-6));
    let mut pose: Vec<Transform> = a
        .skeleton
        .rest()
        .iter()
        .map(|r| Transform::from_translation(r.translation))
        .collect();
    pose[0].translation += root_t;
    let mut buffers = PoseBuffers::new(&a.skeleton);
    buffers.update(&a.skeleton, &pose);
    for (j, (w, b)) in buffers.world.iter().zip(&binds).enumerate() {
        assert!(w.abs_diff_eq(*b, 1e-5), "joint {j}: {w} vs {b}");
    }
    let mut p = vec![Vec3::ZERO; mesh.vertex_count()];
    let mut n = vec![Vec3::ZERO; mesh.vertex_count()];
    skin_cpu(mesh, &buffers.skinning, &mut p, &mut n);
    for (v, (got, want)) in p.iter().zip(mesh.positions()).enumerate() {
        assert!((*got - *want).length() < 1e-5, "vertex {v}");
    }
}

/// `h00 p0 + h10 Δ v0 + h01 p1 + h11 Δ v1` written out.
fn hermite(t0: f32, p0: f32, v0: f32, t1: f32, p1: f32, v1: f32, t: f32) -> f32 {
    let d = t1 - t0;
    let u = (t - t0) / d;
    (2.0 * u * u * u - 3.0 * u * u + 1.0) * p0
        + (u * u * u - 2.0 * u * u + u) * d * v0
        + (-2.0 * u * u * u + 3.0 * u * u) * p1
        + (u * u * u - u * u) * d * v1
}

#[test]
fn wasp_walk_matches_hand_computed_hermite() {
    let (Some(k), Some(w)) = (text("cse169/wasp.skel"), text("cse169/wasp_walk.anim")) else {
        return;
    };
    let s = skel::parse("wasp.skel", &k).unwrap();
    let clip = anim::parse("wasp_walk.anim", &w, &s.skeleton).unwrap();
    assert_eq!((clip.start(), clip.end()), (0.0, 4.0));
    assert_eq!(clip.joint_count(), 23);
    let ch = clip.channels();
    // 3 root translations + 23 × 3 rotations = 72 channels: every joint rotates.
    assert!((0..23).all(|j| clip.animates_rotation(j)));
    assert!(clip.animates_translation(0) && !clip.animates_translation(1));
    let euler = |joint: usize, axis: usize, t: f32| match &ch[joint].rotation {
        Some(RotationChannel::Euler(c)) => c[axis].evaluate(t),
        other => panic!("joint {joint}: {other:?}"),
    };

    // Channel 38 (0-based) = joint 11, z: keys (1, 2.205473 linear) (1.333333, 2.125534 smooth)
    // (1.666667, 1.030814 linear) (2.333333, 1.821344 smooth) (3, 2.205473 linear), cycle.
    // t = 1.5: smooth out-tangent of key 1 over keys 0 and 2, linear in-tangent of key 2.
    let v_out = (1.030814 - 2.205473) / (1.666667 - 1.0);
    let v_in = (1.030814 - 2.125534) / (1.666667 - 1.333333);
    let want = hermite(1.333333, 2.125534, v_out, 1.666667, 1.030814, v_in, 1.5);
    assert!(
        (euler(11, 2, 1.5) - want).abs() < 1e-5,
        "{} vs {want}",
        euler(11, 2, 1.5)
    );
    // t = 0.5 and t = 4.5 (before and past `range`) cycle to 2.5: key 3 (smooth) to key 4.
    let v_out = (2.205473 - 1.030814) / (3.0 - 1.666667);
    let v_in = (2.205473 - 1.821344) / (3.0 - 2.333333);
    let want = hermite(2.333333, 1.821344, v_out, 3.0, 2.205473, v_in, 2.5);
    for t in [0.5f32, 2.5, 4.5, 6.5] {
        assert!(
            (euler(11, 2, t) - want).abs() < 1e-4,
            "t = {t}: {} vs {want}",
            euler(11, 2, t)
        );
    }

    // Channel 10 = joint 2, y: flat keys (−1, 0.087266) (0, −0.087266) (1, 0.087266), cycle.
    let want = hermite(0.0, -0.087266, 0.0, 1.0, 0.087266, 0.0, 0.25);
    for t in [0.25f32, 2.25, 4.25, -1.75] {
        assert!((euler(2, 1, t) - want).abs() < 1e-5, "t = {t}");
    }

    // Channel 2 = root z translation: (0, 0.45 smooth) (2, −0.45 smooth), cycle_offset. Smooth
    // at both ends is the linear rule, so the curve is the line 0.45 − 0.45 t, and each cycle
    // adds −0.9.
    let mut out = vec![Transform::IDENTITY; 23];
    for (t, z) in [
        (1.0f32, 0.0f32),
        (5.0, -1.8),
        (-1.0, 0.9),
        (4.5, 0.45 - 0.45 * 0.5 - 1.8),
    ] {
        clip.sample(t, s.skeleton.rest(), &mut out);
        assert!(
            (out[0].translation.z - z).abs() < 1e-5,
            "t = {t}: {}",
            out[0].translation.z
        );
        // Channel 1 (root y) is the constant 0.95.
        assert!((out[0].translation.y - 0.95).abs() < 1e-6);
    }

    // A whole joint: R = R_z · R_y · R_x from its three curves.
    clip.sample(1.5, s.skeleton.rest(), &mut out);
    let (x, y, z) = (euler(11, 0, 1.5), euler(11, 1, 1.5), euler(11, 2, 1.5));
    let want = Quat::from_rotation_z(z) * Quat::from_rotation_y(y) * Quat::from_rotation_x(x);
    assert!(out[11].rotation.dot(want).abs() > 1.0 - 1e-6);
    // Sampler = exact sampling.
    let mut sampler = clip.sampler();
    let mut fast = vec![Transform::IDENTITY; 23];
    let mut t = -1.0;
    while t < 9.0 {
        sampler.sample(&clip, t, s.skeleton.rest(), &mut fast);
        clip.sample(t, s.skeleton.rest(), &mut out);
        assert_eq!(fast, out, "t = {t}");
        t += 1.0 / 60.0;
    }
}
