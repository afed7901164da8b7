//! The tracker solve against poses whose joint transforms are known: the built-in avatar in
//! poses made by hand, its joints' world transforms given as trackers.

use super::*;
use posecast_proto::trackers::LocomotionClip;
use posecast_rigs::rig::Rig;

fn rig() -> Rig {
    posecast_rigs::builtin::rig().unwrap()
}

fn names(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| (*s).to_owned()).collect()
}

const THREE: [&str; 3] = ["head", "l_hand", "r_hand"];
const SIX: [&str; 6] = ["head", "l_hand", "r_hand", "hips", "l_foot", "r_foot"];

fn joint(rig: &Rig, name: &str) -> usize {
    hanim(rig, name).unwrap()
}

/// Neutral locals (rest translations, identity rotations).
fn neutral(rig: &Rig) -> Vec<Transform> {
    let mut l = rig.skeleton().rest().to_vec();
    for t in &mut l {
        t.rotation = Quat::IDENTITY;
    }
    l
}

fn world_of(rig: &Rig, locals: &[Transform]) -> Vec<Mat4> {
    let mut w = vec![Mat4::IDENTITY; locals.len()];
    forward_kinematics(rig.skeleton(), locals, &mut w);
    w
}

fn transform(world: &[Mat4], j: usize) -> TrackerSample {
    let (_, r, p) = world[j].to_scale_rotation_translation();
    TrackerSample {
        position: p,
        rotation: r,
    }
}

/// A pose a person might hold: spine bent forward and turned, head turned, arms reaching
/// forward with bent elbows, one knee bent.
fn reaching(rig: &Rig) -> Vec<Transform> {
    let mut l = neutral(rig);
    let set = |l: &mut Vec<Transform>, name: &str, q: Quat| l[joint(rig, name)].rotation = q;
    set(&mut l, "vl5", Quat::from_rotation_x(0.15));
    set(&mut l, "vt10", Quat::from_rotation_y(0.2));
    set(
        &mut l,
        "skullbase",
        Quat::from_euler(glam::EulerRot::YXZ, 0.4, 0.2, 0.0),
    );
    // The left shoulder raised and forward: reached only with the clavicle's help.
    set(
        &mut l,
        "l_sternoclavicular",
        Quat::from_euler(glam::EulerRot::XYZ, 0.0, -0.3, 0.25),
    );
    set(
        &mut l,
        "l_shoulder",
        Quat::from_euler(glam::EulerRot::XYZ, -1.0, 0.0, 0.3),
    );
    set(&mut l, "l_elbow", Quat::from_rotation_x(-0.2));
    set(&mut l, "l_wrist", Quat::from_rotation_z(0.3));
    set(
        &mut l,
        "r_shoulder",
        Quat::from_euler(glam::EulerRot::XYZ, -0.6, 0.0, -0.5),
    );
    set(&mut l, "r_elbow", Quat::from_rotation_x(-1.2));
    set(&mut l, "r_wrist", Quat::from_rotation_x(0.4));
    l
}

/// The trackers `list` would read on `world`.
fn read(rig: &Rig, world: &[Mat4], list: &[&str]) -> Vec<(usize, TrackerSample)> {
    list.iter()
        .enumerate()
        .map(|(i, name)| {
            let joint_name = posecast_proto::trackers::STANDARD
                .iter()
                .find(|(t, _)| t == name)
                .map_or(*name, |(_, j)| *j);
            (i, transform(world, joint(rig, joint_name)))
        })
        .collect()
}

/// Solves over the neutral pose (what a clip would have given: the clavicles keep it).
fn solved(rig: &Rig, trackers: &mut Trackers, clock: f64) -> Vec<Mat4> {
    let mut locals = neutral(rig);
    let mut world = vec![Mat4::IDENTITY; locals.len()];
    trackers.solve(rig, Mat4::IDENTITY, clock, &mut locals, &mut world);
    assert!(locals.iter().all(Transform::is_finite));
    world_of(rig, &locals)
}

fn assert_meets(rig: &Rig, got: &[Mat4], want: &[Mat4], joints: &[&str]) {
    for name in joints {
        let j = joint(rig, name);
        let (a, b) = (transform(got, j), transform(want, j));
        let d = a.position.distance(b.position);
        let angle = a.rotation.angle_between(b.rotation).to_degrees();
        assert!(d < 1e-3, "{name}: {d} m from its tracker");
        assert!(angle < 0.5, "{name}: {angle}° from its tracker");
    }
}

#[test]
fn three_trackers_place_head_and_hands_exactly() {
    let rig = rig();
    let want = world_of(&rig, &reaching(&rig));
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    t.set_smoothing(false);
    t.store(&read(&rig, &want, &THREE), 0.0);
    let got = solved(&rig, &mut t, 0.0);
    assert_meets(&rig, &got, &want, &["skullbase", "l_wrist", "r_wrist"]);
    // Feet stay on the floor where they stand at neutral.
    let rest = world_of(&rig, &neutral(&rig));
    for ankle in ["l_ankle", "r_ankle"] {
        let j = joint(&rig, ankle);
        let (g, r) = (transform(&got, j).position, transform(&rest, j).position);
        assert!(
            (g.y - r.y).abs() < 1e-3,
            "{ankle} off the floor: {g} vs {r}"
        );
    }
}

#[test]
fn six_trackers_place_hips_and_feet_too() {
    let rig = rig();
    let mut pose = reaching(&rig);
    let root = joint(&rig, "humanoid_root");
    pose[root].translation += Vec3::new(0.3, -0.15, 0.2);
    pose[root].rotation = Quat::from_rotation_y(0.5);
    pose[joint(&rig, "l_hip")].rotation = Quat::from_rotation_x(-0.6);
    pose[joint(&rig, "l_knee")].rotation = Quat::from_rotation_x(0.9);
    pose[joint(&rig, "r_hip")].rotation = Quat::from_rotation_x(-0.3);
    pose[joint(&rig, "r_knee")].rotation = Quat::from_rotation_x(0.6);
    let want = world_of(&rig, &pose);
    let mut t = Trackers::new(&rig, &names(&SIX), Legs::Planted).unwrap();
    t.set_smoothing(false);
    t.store(&read(&rig, &want, &SIX), 0.0);
    let got = solved(&rig, &mut t, 0.0);
    assert_meets(
        &rig,
        &got,
        &want,
        &[
            "skullbase",
            "l_wrist",
            "r_wrist",
            "humanoid_root",
            "l_ankle",
            "r_ankle",
        ],
    );
    // Solved again from the same trackers: the same pose (no drift, no jitter).
    let again = solved(&rig, &mut t, 1.0 / 60.0);
    for (a, b) in got.iter().zip(&again) {
        assert!(a.abs_diff_eq(*b, 1e-6));
    }
}

#[test]
fn unreachable_hands_reach_straight_and_finite() {
    let rig = rig();
    let mut want = world_of(&rig, &neutral(&rig));
    let l_wrist = joint(&rig, "l_wrist");
    let far = Vec3::new(3.0, 1.4, 2.0);
    want[l_wrist].w_axis = far.extend(1.0);
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    t.set_smoothing(false);
    t.store(&read(&rig, &want, &THREE), 0.0);
    let got = solved(&rig, &mut t, 0.0);
    let [s, e, w] =
        ["l_shoulder", "l_elbow", "l_wrist"].map(|n| transform(&got, joint(&rig, n)).position);
    let (u, f) = ((e - s).normalize(), (w - e).normalize());
    let to_goal = (far - s).normalize();
    assert!(u.dot(f) > 0.9999, "arm not straight: {}", u.dot(f));
    assert!(f.dot(to_goal) > 0.9999, "arm not toward the goal");
    // Absurd but finite values stay finite.
    want[l_wrist].w_axis = Vec3::new(1e6, -1e6, 1e6).extend(1.0);
    t.store(&read(&rig, &want, &THREE), 0.1);
    solved(&rig, &mut t, 0.1);
}

#[test]
fn planted_feet_stay_then_step_after_the_hips() {
    let rig = rig();
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    t.set_smoothing(false);
    let l_ankle = joint(&rig, "l_ankle");
    let mut pose = neutral(&rig);
    let root = joint(&rig, "humanoid_root");
    let start = pose[root].translation;
    let mut last: Option<Vec3> = None;
    let mut moved_while_planted = 0.0f32;
    let mut steps = 0;
    // The user walks 1 m forward over 2 s, then stands; 60 ticks a second.
    for tick in 0..240 {
        let clock = f64::from(tick) / 60.0;
        let walked = (clock as f32 / 2.0).min(1.0);
        pose[root].translation = start + Vec3::Z * walked;
        let want = world_of(&rig, &pose);
        t.store(&read(&rig, &want, &THREE), clock);
        let got = solved(&rig, &mut t, clock);
        let foot = transform(&got, l_ankle).position;
        let stepping = t.feet[0].is_some_and(|f| f.step.is_some());
        if let Some(prev) = last {
            if stepping {
                if t.feet[0].is_some_and(|f| f.step.is_some_and(|(_, _, s)| s == clock)) {
                    steps += 1;
                }
            } else if foot != prev {
                moved_while_planted = moved_while_planted.max(foot.distance(prev));
            }
        }
        last = Some(foot);
    }
    assert!(steps >= 2, "the left foot stepped {steps} times over 1 m");
    assert!(
        moved_while_planted < 0.02,
        "a planted foot slid {moved_while_planted} m in a tick"
    );
    // Standing again, the feet end under the hips.
    let rest = world_of(&rig, &neutral(&rig));
    let want = transform(&rest, l_ankle).position + Vec3::Z;
    let end = last.unwrap();
    assert!(
        end.distance(want) < 0.2 * t.body.leg_length,
        "{end} vs {want}"
    );
}

#[test]
fn calibration_scales_a_taller_user_to_the_avatar() {
    let rig = rig();
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    t.set_smoothing(false);
    let rest = world_of(&rig, &neutral(&rig));
    let head = joint(&rig, "skullbase");
    // A user 10 % taller, standing in the neutral pose, 2 m along x; the controllers are held
    // 5 cm in front of the wrists and turned.
    let user = |w: &[Mat4], list: &[&str]| {
        let mut s = read(&rig, w, list);
        for (i, x) in &mut s {
            x.position = x.position * 1.1 + Vec3::X * 2.0;
            if *i > 0 {
                x.position += Vec3::Z * 0.05;
                x.rotation = (x.rotation * Quat::from_rotation_x(0.7)).normalize();
            }
        }
        s
    };
    t.store(&user(&rest, &THREE), 0.0);
    let c = t
        .calibrate(CalibrationPose::Neutral, Mat4::IDENTITY)
        .unwrap();
    let avatar_head = transform(&rest, head).position.y;
    assert!((c.scale - 1.0 / 1.1).abs() < 1e-4, "scale {}", c.scale);
    assert!((c.user_height - avatar_head * 1.1).abs() < 1e-4);
    // In the calibration pose the solved avatar stands in its neutral pose where the user is.
    let got = solved(&rig, &mut t, 0.0);
    for name in ["skullbase", "l_wrist", "r_wrist", "l_elbow"] {
        let j = joint(&rig, name);
        let want = transform(&rest, j).position + Vec3::X * 2.0;
        let g = transform(&got, j);
        // The elbow of an arm hanging straight sits within the few millimetres its bend
        // needs to keep a side (a straight limb has no bend plane).
        let within = if name == "l_elbow" { 3e-3 } else { 1e-3 };
        assert!(
            g.position.distance(want) < within,
            "{name}: {} vs {want}",
            g.position
        );
        assert!(
            g.rotation.angle_between(Quat::IDENTITY).to_degrees() < 0.5,
            "{name} turned"
        );
    }
    // A T-pose measures the arms: a user whose arms are 20 % longer than the body says.
    let mut tpose = neutral(&rig);
    tpose[joint(&rig, "l_shoulder")].rotation = Quat::from_rotation_z(PI / 2.0);
    tpose[joint(&rig, "r_shoulder")].rotation = Quat::from_rotation_z(-PI / 2.0);
    let tw = world_of(&rig, &tpose);
    let mut samples = read(&rig, &tw, &THREE);
    let centre = transform(&tw, head).position;
    for (i, x) in &mut samples {
        if *i > 0 {
            let d = x.position - centre;
            x.position = centre + Vec3::new(d.x * 1.2, d.y, d.z);
        }
    }
    t.store(&samples, 1.0);
    let c = t.calibrate(CalibrationPose::TPose, Mat4::IDENTITY).unwrap();
    assert!((c.scale - 1.0).abs() < 1e-4);
    assert!(
        c.arm_scale < 0.9 && c.arm_scale > 0.75,
        "arm scale {}",
        c.arm_scale
    );
    // A refused calibration (the head on the floor) keeps the last one.
    let mut low = samples.clone();
    low[0].1.position.y = 0.05;
    t.store(&low, 1.5);
    assert_eq!(
        t.calibrate(CalibrationPose::Neutral, Mat4::IDENTITY),
        Err(TrackerError::TooLow(0.05))
    );
    assert_eq!((t.scale, t.arm_scale), (c.scale, c.arm_scale));
    // An A-pose (arms 45° down) of a user 10 % larger in every way: both scales 1/1.1.
    let mut apose = neutral(&rig);
    apose[joint(&rig, "l_shoulder")].rotation = Quat::from_rotation_z(PI / 4.0);
    apose[joint(&rig, "r_shoulder")].rotation = Quat::from_rotation_z(-PI / 4.0);
    let aw = world_of(&rig, &apose);
    let mut samples = read(&rig, &aw, &THREE);
    for (_, x) in &mut samples {
        x.position *= 1.1;
    }
    t.store(&samples, 2.0);
    let c = t.calibrate(CalibrationPose::APose, Mat4::IDENTITY).unwrap();
    assert!((c.scale - 1.0 / 1.1).abs() < 1e-4, "scale {}", c.scale);
    assert!(
        (c.arm_scale - 1.0 / 1.1).abs() < 1e-3,
        "arm scale {}",
        c.arm_scale
    );
    // Solved in that pose, the avatar holds its own A-pose.
    let got = solved(&rig, &mut t, 2.0);
    for name in ["l_wrist", "r_wrist"] {
        let j = joint(&rig, name);
        let d = transform(&got, j)
            .position
            .distance(transform(&aw, j).position);
        assert!(d < 1e-3, "{name} {d} m from the avatar's A-pose");
    }
}

#[test]
fn the_filter_smooths_a_still_tracker_and_follows_a_moving_one() {
    let rig = rig();
    let rest = world_of(&rig, &neutral(&rig));
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    let mut seed = 7u32;
    let mut noise = || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (f64::from(seed >> 8) / f64::from(1u32 << 24)) as f32 - 0.5
    };
    let l_wrist = joint(&rig, "l_wrist");
    let mut input_jitter = 0.0;
    let mut output_jitter = 0.0;
    let mut prev_in: Option<Vec3> = None;
    let mut prev_out: Option<Vec3> = None;
    // 90 Hz trackers with ±2 mm noise, ticks at 60 Hz.
    for k in 0..180 {
        let time = f64::from(k) / 90.0;
        let mut s = read(&rig, &rest, &THREE);
        for (_, x) in &mut s {
            x.position += Vec3::new(noise(), noise(), noise()) * 0.004;
        }
        if let Some(p) = prev_in {
            input_jitter += s[1].1.position.distance(p);
        }
        prev_in = Some(s[1].1.position);
        t.store(&s, time);
        if k % 3 == 0 && k > 90 {
            let got = solved(&rig, &mut t, time);
            let w = transform(&got, l_wrist).position;
            if let Some(p) = prev_out {
                output_jitter += w.distance(p);
            }
            prev_out = Some(w);
        }
    }
    let input = input_jitter / 179.0;
    let output = output_jitter / 29.0;
    assert!(
        output < input / 3.0,
        "jitter in {input} m, out {output} m per sample"
    );
    // A hand moving at 0.5 m/s for a second lags little.
    for k in 0..=90 {
        let time = 2.0 + f64::from(k) / 90.0;
        let mut s = read(&rig, &rest, &THREE);
        s[1].1.position += Vec3::new(0.0, 0.3, 0.4) * (f64::from(k) / 90.0) as f32;
        t.store(&s, time);
    }
    let got = solved(&rig, &mut t, 3.0);
    let w = transform(&got, l_wrist).position;
    let want = transform(&rest, l_wrist).position + Vec3::new(0.0, 0.3, 0.4);
    assert!(
        w.distance(want) < 0.03,
        "lags {} m behind",
        w.distance(want)
    );
}

#[test]
fn bad_tracker_lists_are_refused() {
    let rig = rig();
    let err = |list: &[&str]| Trackers::new(&rig, &names(list), Legs::Planted).unwrap_err();
    assert_eq!(err(&["head", "l_hand"]), TrackerError::Required("r_hand"));
    assert_eq!(
        err(&["head", "l_hand", "r_hand", "tail"]),
        TrackerError::Unknown("tail".into())
    );
    assert_eq!(
        err(&["head", "l_hand", "r_hand", "hips", "hips"]),
        TrackerError::Duplicate("hips".into())
    );
    assert_eq!(
        err(&["head", "l_hand", "r_hand", "humanoid_root"]),
        TrackerError::NoChain("humanoid_root".into())
    );
    // A named joint is reached as a goal.
    let ok = Trackers::new(
        &rig,
        &names(&["head", "l_hand", "r_hand", "l_elbow"]),
        Legs::Planted,
    );
    assert!(ok.is_ok());
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    assert_eq!(
        t.calibrate(CalibrationPose::Neutral, Mat4::IDENTITY),
        Err(TrackerError::NoSample("head".into()))
    );
}

#[test]
fn locomotion_legs_play_the_clip_the_hips_speed_picks() {
    use crate::avatar::live::LivePose;
    use crate::avatar::{Avatar, LOCOMOTION_LAYER};
    use posecast_proto::command::OnRelease;
    use posecast_proto::msg::AvatarId;
    use std::sync::Arc;
    use std::time::{Duration, Instant};

    let rig = Arc::new(rig());
    let mut a = Avatar::new(AvatarId("a".into()), 1, rig.clone());
    let mut live = LivePose::new(
        1,
        OnRelease::Clip,
        rig.clone(),
        &rig,
        &a.locals,
        Duration::from_secs(3600),
    )
    .unwrap();
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Locomotion).unwrap();
    let clips = [
        LocomotionClip {
            clip: "idle".into(),
            speed: 0.0,
        },
        LocomotionClip {
            clip: "walk".into(),
            speed: 1.2,
        },
    ];
    t.set_locomotion(&rig, &clips).unwrap();
    live.trackers = Some(t);
    a.live = Some(live);
    let rest = world_of(&rig, &neutral(&rig));
    let l_knee = joint(&rig, "l_knee");
    // The user walks forward at 1.5 m/s for 3 s, then stands for 2 s; 60 ticks a second.
    let mut walking_at_3s = None;
    for tick in 0..=300u32 {
        let clock = f64::from(tick) / 60.0;
        let walked = 1.5 * clock.min(3.0) as f32;
        let mut s = read(&rig, &rest, &THREE);
        for (_, x) in &mut s {
            x.position.z += walked;
        }
        let time_us = Some((clock * 1e6) as u64);
        let live = a.live.as_mut().unwrap();
        assert!(live.store_trackers(&s, time_us, Instant::now()));
        a.tick(clock);
        if tick == 180 {
            let layer = a.layers.iter().find(|l| l.name == LOCOMOTION_LAYER);
            let playing = layer
                .and_then(|l| l.player.current())
                .expect("a locomotion layer");
            walking_at_3s = Some((playing.clip.name().to_owned(), playing.speed()));
            // The legs are the walk clip's at the layer's time (faded in long ago).
            let mut sample = rig.skeleton().rest().to_vec();
            let time = playing.clip.start() + playing.clip_time();
            playing
                .clip
                .sample(time, rig.skeleton().rest(), &mut sample);
            let angle = a.locals[l_knee]
                .rotation
                .angle_between(sample[l_knee].rotation)
                .to_degrees();
            assert!(angle < 0.01, "the knee is {angle}° off the walk clip's");
        }
    }
    let (clip, rate) = walking_at_3s.unwrap();
    assert_eq!(clip, "walk");
    assert!(
        (rate - 1.25).abs() < 0.05,
        "walk (1.2 m/s) played at {rate} for 1.5 m/s"
    );
    let playing = a
        .layers
        .iter()
        .find(|l| l.name == LOCOMOTION_LAYER && !l.stopping())
        .and_then(|l| l.player.current())
        .unwrap();
    assert_eq!(playing.clip.name(), "idle", "standing still for 2 s");
    // The drive ends: the layer fades out and goes.
    a.release_drive();
    for tick in 301..=340u32 {
        a.tick(f64::from(tick) / 60.0);
    }
    assert!(a.layers.iter().all(|l| l.name != LOCOMOTION_LAYER));
}

#[test]
fn locomotion_lists_are_checked() {
    let rig = rig();
    let clip = |name: &str, speed: f32| LocomotionClip {
        clip: name.into(),
        speed,
    };
    let mut planted = Trackers::new(&rig, &names(&THREE), Legs::Planted).unwrap();
    assert!(planted.set_locomotion(&rig, &[clip("walk", 1.0)]).is_err());
    let mut t = Trackers::new(&rig, &names(&THREE), Legs::Locomotion).unwrap();
    for bad in [
        vec![],
        vec![clip("moonwalk", 1.0)],
        vec![clip("walk", f32::NAN)],
        vec![clip("walk", -1.0)],
        vec![clip("walk", 1e9)],
        vec![clip("walk", 1.0); 9],
    ] {
        let err = t.set_locomotion(&rig, &bad).unwrap_err();
        assert!(matches!(err, TrackerError::Locomotion(_)), "{err:?}");
    }
    assert!(t.gait().is_none());
}
