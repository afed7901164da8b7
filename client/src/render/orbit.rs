//! The viewer's camera controls: orbit about a target, pan, zoom, follow an avatar, and pick one
//! under the mouse. Pure state and geometry (no window), so the controls are tested without a
//! display; [`super::viewer`] maps mouse and keys onto them.

use super::bounds::Aabb;
use super::camera::Camera;
use glam::{Mat4, Vec2, Vec3};

/// Highest and lowest elevation of the eye above the target's horizon, radians (short of the
/// poles, where "up" would be undefined).
const MAX_PITCH: f32 = 89f32.to_radians();
/// Nearest and farthest the eye may be from the target, metres.
const MIN_DISTANCE: f32 = 0.05;
const MAX_DISTANCE: f32 = 10_000.0;

/// A camera orbiting `target` at `distance`, `yaw` about +Y (0 = looking along −Z from +Z) and
/// `pitch` above the horizon.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orbit {
    /// The point looked at and orbited, world space, metres.
    pub target: Vec3,
    /// Eye distance from the target, metres.
    pub distance: f32,
    /// Azimuth of the eye about +Y, radians.
    pub yaw: f32,
    /// Elevation of the eye above the target, radians, within ±89°.
    pub pitch: f32,
    /// Vertical field of view, radians.
    pub fov_y: f32,
}

impl Orbit {
    /// The orbit that sees what `camera` sees (same eye, target and field of view).
    #[must_use]
    pub fn from_camera(camera: &Camera) -> Self {
        let offset = camera.eye - camera.target;
        let distance = offset.length().clamp(MIN_DISTANCE, MAX_DISTANCE);
        let dir = offset.normalize_or(Vec3::Z);
        Self {
            target: camera.target,
            distance,
            yaw: dir.x.atan2(dir.z),
            pitch: dir.y.clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH),
            fov_y: camera.fov_y,
        }
    }

    /// Unit direction from the target to the eye.
    #[must_use]
    pub fn direction(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        Vec3::new(sy * cp, sp, cy * cp)
    }

    /// Where the eye is.
    #[must_use]
    pub fn eye(&self) -> Vec3 {
        self.target + self.direction() * self.distance
    }

    /// The camera, with clip planes that keep a scene of `radius` metres about the target in
    /// view at any zoom.
    #[must_use]
    pub fn camera(&self, radius: f32) -> Camera {
        let radius = radius.max(1e-3);
        Camera {
            eye: self.eye(),
            target: self.target,
            fov_y: self.fov_y,
            near: (self.distance - 2.0 * radius)
                .max(self.distance * 0.01)
                .max(1e-3),
            far: self.distance + 8.0 * radius,
        }
    }

    /// Turns the eye about the target: `yaw` about +Y, `pitch` up (clamped short of the poles).
    pub fn rotate(&mut self, yaw: f32, pitch: f32) {
        if yaw.is_finite() && pitch.is_finite() {
            self.yaw = (self.yaw + yaw).rem_euclid(std::f32::consts::TAU);
            self.pitch = (self.pitch + pitch).clamp(-MAX_PITCH, MAX_PITCH);
        }
    }

    /// Moves eye and target together across the view: `right` and `up` in fractions of the
    /// view's height at the target's distance (so a drag of the whole window's height moves
    /// the scene by as much as it shows).
    pub fn pan(&mut self, right: f32, up: f32) {
        if !(right.is_finite() && up.is_finite()) {
            return;
        }
        let forward = -self.direction();
        let right_axis = forward.cross(Vec3::Y).normalize_or(Vec3::X);
        let up_axis = right_axis.cross(forward);
        let height = 2.0 * self.distance * (self.fov_y * 0.5).tan();
        self.target += (right_axis * right + up_axis * up) * height;
    }

    /// Moves the eye towards (`factor` < 1) or away from (> 1) the target.
    pub fn zoom(&mut self, factor: f32) {
        if factor.is_finite() && factor > 0.0 {
            self.distance = (self.distance * factor).clamp(MIN_DISTANCE, MAX_DISTANCE);
        }
    }

    /// Keeps following something that moved from `from` to `to`: eye and target move with it.
    pub fn follow(&mut self, from: Vec3, to: Vec3) {
        let d = to - from;
        if d.is_finite() {
            self.target += d;
        }
    }
}

/// The world-space ray under a point of the window: `pixel` in physical pixels from the top
/// left, `size` the window's size. Returns `(origin, unit direction)`.
#[must_use]
pub fn ray(camera: &Camera, pixel: Vec2, size: Vec2) -> Option<(Vec3, Vec3)> {
    let aspect = size.x / size.y;
    let inverse: Mat4 = camera.view_proj(aspect).inverse();
    let ndc = Vec2::new(2.0 * pixel.x / size.x - 1.0, 1.0 - 2.0 * pixel.y / size.y);
    let near = inverse.project_point3(ndc.extend(0.0));
    let far = inverse.project_point3(ndc.extend(1.0));
    let direction = (far - near).normalize_or_zero();
    (near.is_finite() && direction != Vec3::ZERO).then_some((near, direction))
}

/// Distance along the ray to where it enters `b` (0 when it starts inside), or `None`.
#[must_use]
pub fn hit(b: &Aabb, origin: Vec3, direction: Vec3) -> Option<f32> {
    let inv = direction.recip();
    let t1 = (b.min - origin) * inv;
    let t2 = (b.max - origin) * inv;
    let near = t1.min(t2).max_element();
    let far = t1.max(t2).min_element();
    (far >= near.max(0.0)).then_some(near.max(0.0))
}

/// The nearest of `boxes` the ray hits: the avatar under the mouse.
#[must_use]
pub fn pick<K: Copy>(
    boxes: impl IntoIterator<Item = (K, Aabb)>,
    origin: Vec3,
    direction: Vec3,
) -> Option<K> {
    boxes
        .into_iter()
        .filter_map(|(k, b)| hit(&b, origin, direction).map(|t| (k, t)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(k, _)| k)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::FRAC_PI_2;

    fn close(a: Vec3, b: Vec3) -> bool {
        a.distance(b) < 1e-4
    }

    fn orbit() -> Orbit {
        Orbit {
            target: Vec3::new(1.0, 1.0, 0.0),
            distance: 4.0,
            yaw: 0.0,
            pitch: 0.0,
            fov_y: 40f32.to_radians(),
        }
    }

    #[test]
    fn a_camera_round_trips_through_its_orbit() {
        let camera = Camera::framing(
            &Aabb {
                min: Vec3::new(-0.5, 0.0, -0.3),
                max: Vec3::new(0.5, 1.8, 0.3),
            },
            1.5,
        );
        let orbit = Orbit::from_camera(&camera);
        let back = orbit.camera(1.0);
        assert!(
            close(back.eye, camera.eye),
            "{} vs {}",
            back.eye,
            camera.eye
        );
        assert!(close(back.target, camera.target));
    }

    #[test]
    fn orbiting_turns_the_eye_about_the_target_at_the_same_distance() {
        let mut o = orbit();
        // Yaw 0, pitch 0: the eye is on +Z of the target (derived by hand from `direction`).
        assert!(close(o.eye(), Vec3::new(1.0, 1.0, 4.0)));
        o.rotate(FRAC_PI_2, 0.0);
        assert!(close(o.eye(), Vec3::new(5.0, 1.0, 0.0)), "{}", o.eye());
        o.rotate(0.0, 30f32.to_radians());
        let e = o.eye();
        assert!((e.distance(o.target) - 4.0).abs() < 1e-4);
        assert!((e.y - (1.0 + 4.0 * 0.5)).abs() < 1e-4, "{e}");
        // Past the pole: clamped, the eye never flips over.
        o.rotate(0.0, 10.0);
        assert!((o.pitch - MAX_PITCH).abs() < 1e-6);
        assert!(o.eye().is_finite());
    }

    #[test]
    fn panning_moves_eye_and_target_across_the_view() {
        let mut o = orbit();
        let before = o.camera(1.0);
        o.pan(0.5, 0.0);
        let after = o.camera(1.0);
        let moved = after.target - before.target;
        // Looking along −Z, "right" is +X; half the view's height at distance 4 and 40°.
        let expected = 0.5 * 2.0 * 4.0 * 20f32.to_radians().tan();
        assert!(close(moved, Vec3::new(expected, 0.0, 0.0)), "{moved}");
        assert!(close(after.eye - before.eye, moved));
        o.pan(0.0, 0.25);
        assert!(o.target.y > 1.0);
    }

    #[test]
    fn zoom_scales_the_distance_within_limits() {
        let mut o = orbit();
        o.zoom(0.5);
        assert!((o.distance - 2.0).abs() < 1e-6);
        o.zoom(1e-9);
        assert!((o.distance - MIN_DISTANCE).abs() < 1e-6);
        o.zoom(f32::INFINITY);
        o.zoom(-1.0);
        assert!((o.distance - MIN_DISTANCE).abs() < 1e-6);
        assert!(o.camera(1.0).near > 0.0);
    }

    #[test]
    fn following_keeps_the_view_of_a_moving_avatar() {
        let mut o = orbit();
        let offset = o.eye() - o.target;
        o.follow(Vec3::new(0.0, 0.9, 0.0), Vec3::new(2.0, 0.9, -3.0));
        assert!(close(o.target, Vec3::new(3.0, 1.0, -3.0)));
        assert!(close(o.eye() - o.target, offset));
    }

    #[test]
    fn the_box_under_the_mouse_is_picked_nearest_first() {
        let camera = orbit().camera(3.0);
        let size = Vec2::new(800.0, 600.0);
        let boxes = [
            (
                "left",
                Aabb {
                    min: Vec3::new(-0.6, 0.0, -0.2),
                    max: Vec3::new(0.0, 1.8, 0.2),
                },
            ),
            (
                "centre",
                Aabb {
                    min: Vec3::new(0.7, 0.1, -0.2),
                    max: Vec3::new(1.3, 1.9, 0.2),
                },
            ),
            (
                "behind",
                Aabb {
                    min: Vec3::new(0.7, 0.1, -3.2),
                    max: Vec3::new(1.3, 1.9, -2.8),
                },
            ),
        ];
        // Project each box's centre to the window and click there.
        let click = |p: Vec3| {
            let ndc = camera.view_proj(size.x / size.y).project_point3(p);
            Vec2::new((ndc.x + 1.0) * 0.5 * size.x, (1.0 - ndc.y) * 0.5 * size.y)
        };
        for (name, b) in &boxes[..2] {
            let (o, d) = ray(&camera, click(b.center()), size).unwrap();
            assert_eq!(pick(boxes.iter().copied(), o, d), Some(*name));
        }
        // A box behind the eye is not under the mouse, though the ray's line meets it.
        let mut with_behind_eye = boxes.to_vec();
        with_behind_eye.push((
            "behind the eye",
            Aabb {
                min: Vec3::new(0.7, 0.1, 5.0),
                max: Vec3::new(1.3, 1.9, 6.0),
            },
        ));
        let (o, d) = ray(&camera, click(boxes[1].1.center()), size).unwrap();
        assert_eq!(pick(with_behind_eye, o, d), Some("centre"));
        // "behind" is hidden behind "centre": the nearer one wins.
        let (o, d) = ray(&camera, click(boxes[2].1.center()), size).unwrap();
        assert_eq!(pick(boxes.iter().copied(), o, d), Some("centre"));
        // The sky picks nothing.
        let (o, d) = ray(&camera, Vec2::new(5.0, 5.0), size).unwrap();
        assert_eq!(pick(boxes.iter().copied(), o, d), None);
    }
}
