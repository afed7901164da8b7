//! What IK goals cost a tick: the built-in avatar (23 joints) playing `walk`, evaluated with
//! no goal, a hand goal (closed-form limb with a rotation and a pole), both hands and a gaze
//! (three goals), and a five-joint FABRIK chain up the spine to the head.
//!
//! Run: `cargo bench -p posecast-sim --bench ik`. Prints µs per evaluation; the goals' cost is
//! the difference from the first row.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use criterion::{Criterion, criterion_group, criterion_main};
use glam::{Mat4, Quat, Vec3};
use posecast_proto::msg::AvatarId;
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::goals::{self, GazeGoal, IkGoal};
use posecast_sim::avatar::playback::Layer;
use std::hint::black_box;
use std::sync::Arc;

fn goal(avatar: &Avatar, effector: &str, chain: Option<usize>, position: Vec3) -> IkGoal {
    let (effector, solver) = goals::solver(&avatar.rig, effector, chain).unwrap();
    IkGoal {
        effector,
        solver,
        position,
        rotation: Some(Quat::from_rotation_y(0.5)),
        pole: Some(Vec3::new(0.0, 0.0, -2.0)),
        weight: 1.0,
        relative_to: None,
        chain,
        frame: Mat4::IDENTITY,
    }
}

fn ik(c: &mut Criterion) {
    let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
    let walk = rig.clip("walk").unwrap().clone();
    let walking = || {
        let mut a = Avatar::new(AvatarId("a".into()), 1, rig.clone());
        a.play(Layer::new(walk.clone(), None, 0.0, 1.0, true), 0.0);
        a
    };
    let mut cases: Vec<(&str, Avatar)> = Vec::new();
    cases.push(("no goal", walking()));
    let mut one = walking();
    one.goals
        .set(goal(&one, "l_wrist", None, Vec3::new(0.3, 1.1, 0.35)));
    cases.push(("one hand (two-bone)", one));
    let mut three = walking();
    three
        .goals
        .set(goal(&three, "l_wrist", None, Vec3::new(0.3, 1.1, 0.35)));
    three
        .goals
        .set(goal(&three, "r_wrist", None, Vec3::new(-0.3, 1.2, 0.3)));
    three.goals.gaze = Some(GazeGoal {
        joints: goals::gaze(&three.rig).unwrap(),
        target: Vec3::new(1.0, 1.7, 2.0),
        weight: 1.0,
        relative_to: None,
        frame: Mat4::IDENTITY,
    });
    cases.push(("two hands and a gaze", three));
    let mut spine = walking();
    spine.goals.set(goal(
        &spine,
        "skullbase",
        Some(5),
        Vec3::new(0.1, 1.55, 0.25),
    ));
    cases.push(("5-joint chain (FABRIK)", spine));
    let mut group = c.benchmark_group("ik");
    for (name, mut avatar) in cases {
        let mut clock = 0.0;
        group.bench_function(name, |b| {
            b.iter(|| {
                clock += 1.0 / 60.0;
                avatar.tick(black_box(clock));
            });
        });
    }
    group.finish();
}

criterion_group!(benches, ik);
criterion_main!(benches);
