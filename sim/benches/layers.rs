//! What clip layers cost a tick: the built-in avatar (23 joints) playing `walk`, with no layer,
//! a masked layer (the right arm waving), an additive layer over every joint (`idle` added at
//! half weight), and both.
//!
//! Run: `cargo bench -p posecast-sim --bench layers`. Prints µs per avatar-tick; a layer's
//! cost is the difference from the first row.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use criterion::{Criterion, criterion_group, criterion_main};
use posecast_proto::command::{AdditiveReference, JointMask};
use posecast_proto::msg::AvatarId;
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::layers::{ClipLayer, LayerSpec, owned_joints};
use posecast_sim::avatar::playback::Layer;
use std::hint::black_box;
use std::sync::Arc;

fn layers(c: &mut Criterion) {
    let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
    let clip = |name: &str| rig.clip(name).unwrap().clone();
    let walking = || {
        let mut a = Avatar::new(AvatarId("a".into()), 1, rig.clone());
        a.play(Layer::new(clip("walk"), None, 0.0, 1.0, true), 0.0);
        a
    };
    let layer =
        |a: &mut Avatar, name: &str, clip_name: &str, mask: Option<JointMask>, additive: bool| {
            let spec = LayerSpec {
                owned: owned_joints(&a.rig, mask.as_ref()).unwrap(),
                mask,
                additive,
                reference: AdditiveReference::Rest,
                weight: if additive { 0.5 } else { 1.0 },
            };
            let played = Layer::new(clip(clip_name), None, 0.0, 1.0, true);
            a.layers
                .push(ClipLayer::new(name.into(), played, spec, 0.0, 0.0));
        };
    let arm = || {
        Some(JointMask {
            joints: vec!["r_sternoclavicular".into()],
            except: Vec::new(),
        })
    };
    let mut cases: Vec<(&str, Avatar)> = vec![("no layer", walking())];
    let mut masked = walking();
    layer(&mut masked, "arm", "wave", arm(), false);
    cases.push(("masked layer (right arm)", masked));
    let mut additive = walking();
    layer(&mut additive, "breath", "idle", None, true);
    cases.push(("additive layer (all joints)", additive));
    let mut both = walking();
    layer(&mut both, "arm", "wave", arm(), false);
    layer(&mut both, "breath", "idle", None, true);
    cases.push(("both", both));
    let mut group = c.benchmark_group("layers");
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

criterion_group!(benches, layers);
criterion_main!(benches);
