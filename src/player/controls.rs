//! The player's camera controller: orbit about a target, fly, pan and dolly, with the horizon
//! kept level with the up axis (no roll). Cameras are OpenCV (x right, y down, z forward).
use glam::Vec3;

use crate::model::camera::Camera;

/// The player's camera: a target point, a distance and yaw/pitch of the eye about the up axis.
/// Orbit moves the eye around the target; fly moves shift both.
#[derive(Clone, Debug)]
pub struct ViewCamera {
    pub target: Vec3,
    pub distance: f32,
    /// Azimuth of the eye around the target (radians).
    pub yaw: f32,
    /// Elevation of the eye above the target's horizontal plane (radians, within ±89°).
    pub pitch: f32,
    /// Horizontal field of view (radians).
    pub fov_x: f32,
    up: Vec3,
    e1: Vec3,
    e2: Vec3,
}

const MAX_PITCH: f32 = 89.0 * std::f32::consts::PI / 180.0;

impl ViewCamera {
    /// The view of `start` (its eye, viewing direction and horizontal field of view), with the
    /// target where the viewing ray passes closest to `centre`. `up` is the world's up axis.
    pub fn from_camera(start: &Camera, centre: Vec3, up: Vec3) -> ViewCamera {
        let up = up.normalize();
        let (e1, e2) = crate::model::camera::horizontal_axes(up);
        let c2w = start.viewmat.inverse();
        let eye = c2w.w_axis.truncate();
        let forward = c2w.z_axis.truncate().normalize();
        let along = (centre - eye).dot(forward);
        let distance = if along > 1e-3 { along } else { (centre - eye).length().max(1e-3) };
        let dir = -forward;
        ViewCamera {
            target: eye + forward * distance,
            distance,
            yaw: dir.dot(e2).atan2(dir.dot(e1)),
            pitch: dir.dot(up).clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH),
            fov_x: 2.0 * (0.5 * start.width as f32 / start.fx).atan(),
            up,
            e1,
            e2,
        }
    }

    /// Unit vector from the target to the eye.
    fn eye_dir(&self) -> Vec3 {
        (self.e1 * self.yaw.cos() + self.e2 * self.yaw.sin()) * self.pitch.cos() + self.up * self.pitch.sin()
    }

    /// The world's up axis (unit).
    pub fn up(&self) -> Vec3 {
        self.up
    }

    pub fn eye(&self) -> Vec3 {
        self.target + self.eye_dir() * self.distance
    }

    /// The camera for a `width` × `height` image (square pixels, centred principal point).
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        crate::model::camera::level_camera(
            "view".into(),
            self.eye(),
            -self.eye_dir(),
            self.up,
            width,
            height,
            self.fov_x,
        )
    }

    /// Turns the eye around the target.
    pub fn orbit(&mut self, d_yaw: f32, d_pitch: f32) {
        self.yaw += d_yaw;
        self.pitch = (self.pitch + d_pitch).clamp(-MAX_PITCH, MAX_PITCH);
    }

    /// Turns the view around the eye (the target moves).
    pub fn look(&mut self, d_yaw: f32, d_pitch: f32) {
        let eye = self.eye();
        self.orbit(d_yaw, d_pitch);
        self.target = eye - self.eye_dir() * self.distance;
    }

    /// Moves eye and target by (right, up, forward) × distance.
    pub fn fly(&mut self, right: f32, up: f32, forward: f32) {
        let z = -self.eye_dir();
        let x = z.cross(self.up).normalize();
        self.target += (x * right + self.up * up + z * forward) * self.distance;
    }

    /// Moves the eye towards (factor < 1) or away from the target.
    pub fn dolly(&mut self, factor: f32) {
        self.distance = (self.distance * factor).max(1e-4);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_camera_reproduces_a_level_start_camera() {
        let cams = crate::model::camera::Orbit {
            center: Vec3::new(0.3, -0.2, 0.1),
            distance: 4.0,
            up: crate::model::camera::UpAxis::NegY,
            elevation_deg: 25.0,
            fov_x_deg: 50.0,
        }
        .cameras(5, 320, 240);
        for c in &cams {
            let v = ViewCamera::from_camera(c, Vec3::new(0.3, -0.2, 0.1), -Vec3::Y);
            let back = v.camera(320, 240);
            assert!((back.fx - c.fx).abs() < 1e-3 * c.fx);
            let d = (back.viewmat - c.viewmat).abs().to_cols_array().into_iter().fold(0.0f32, f32::max);
            assert!(d < 1e-4, "{d}");
            assert!((v.distance - 4.0).abs() < 1e-4);
        }
    }

    #[test]
    fn orbit_keeps_the_target_and_look_keeps_the_eye() {
        let c = crate::model::camera::orbit_around_points(
            &[[0.0; 3], [1.0, 1.0, 1.0]],
            1,
            crate::model::camera::UpAxis::PosZ,
            64,
            48,
        );
        let mut v = ViewCamera::from_camera(&c[0], Vec3::splat(0.5), Vec3::Z);
        let t = v.target;
        v.orbit(0.3, 0.2);
        assert!((v.target - t).length() < 1e-6 && (v.eye() - t).length() - v.distance < 1e-5);
        let e2 = v.eye();
        v.look(-0.5, 0.1);
        assert!((v.eye() - e2).length() < 1e-4 && (v.target - t).length() > 1e-3);
        v.orbit(0.0, 10.0);
        assert!(v.pitch <= MAX_PITCH);
    }
}
