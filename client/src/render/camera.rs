//! A perspective camera, and framing a box so the whole scene is in view.

use super::bounds::Aabb;
use glam::{Mat4, Vec3};

/// A right-handed perspective camera looking from `eye` at `target`, Y up, depth 0..1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Position, world space, metres.
    pub eye: Vec3,
    /// Point looked at, world space.
    pub target: Vec3,
    /// Vertical field of view, radians.
    pub fov_y: f32,
    /// Near clip distance from the eye, metres.
    pub near: f32,
    /// Far clip distance from the eye, metres.
    pub far: f32,
}

impl Default for Camera {
    /// Frames a 2 m cube standing on the ground at the origin.
    fn default() -> Self {
        Self::framing(
            &Aabb {
                min: Vec3::new(-0.5, 0.0, -0.5),
                max: Vec3::new(0.5, 2.0, 0.5),
            },
            16.0 / 9.0,
        )
    }
}

impl Camera {
    /// Direction from the target towards the eye: in front (+Z, where avatars face), to the
    /// right and a little above, so limbs do not hide each other and the ground grid shows.
    pub const VIEW_DIRECTION: Vec3 = Vec3::new(0.45, 0.3, 1.0);

    /// A camera from [`Camera::VIEW_DIRECTION`] at the distance where the box's bounding sphere
    /// fits the narrower of the two fields of view, with 5 % margin.
    #[must_use]
    pub fn framing(bounds: &Aabb, aspect: f32) -> Self {
        let fov_y = 40f32.to_radians();
        let centre = bounds.center();
        let radius = (bounds.size() * 0.5).max(1e-3);
        let aspect = if aspect.is_finite() && aspect > 0.0 {
            aspect
        } else {
            1.0
        };
        let fov_x = 2.0 * ((fov_y * 0.5).tan() * aspect).atan();
        let half = 0.5 * fov_y.min(fov_x);
        let distance = 1.05 * radius / half.sin();
        Self {
            eye: centre + Self::VIEW_DIRECTION.normalize() * distance,
            target: centre,
            fov_y,
            near: (distance - 2.0 * radius).max(distance * 0.01),
            far: distance + 8.0 * radius,
        }
    }

    /// World-to-view.
    #[must_use]
    pub fn view(&self) -> Mat4 {
        Mat4::look_at_rh(self.eye, self.target, Vec3::Y)
    }

    /// World-to-clip for a viewport of `aspect` = width / height.
    #[must_use]
    pub fn view_proj(&self, aspect: f32) -> Mat4 {
        Mat4::perspective_rh(self.fov_y, aspect.max(1e-6), self.near, self.far) * self.view()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn framed_box_is_inside_the_view() {
        for aspect in [0.5, 1.0, 16.0 / 9.0, 3.0] {
            let bounds = Aabb {
                min: Vec3::new(-0.3, 0.0, -0.2),
                max: Vec3::new(0.4, 1.8, 0.3),
            };
            let camera = Camera::framing(&bounds, aspect);
            let vp = camera.view_proj(aspect);
            for corner in bounds.corners() {
                let clip = vp * corner.extend(1.0);
                let ndc = clip.truncate() / clip.w;
                assert!(clip.w > 0.0);
                assert!(
                    ndc.x.abs() <= 1.0 && ndc.y.abs() <= 1.0,
                    "{corner} -> {ndc}"
                );
                assert!(ndc.z >= 0.0 && ndc.z <= 1.0, "{corner} -> depth {}", ndc.z);
            }
        }
    }
}
