//! The encoder's answer for one frame, as the ONNX graph's outputs fill it: a leaf that the
//! runtime (which fills it), the test-time yaw copies (which fuse several) and the tracker (which
//! reads it) share without depending on each other.

/// The encoder's outputs for one frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Encoding {
    pub q: [f32; 4],
    pub x_c: Vec<f32>,
    pub z_r_mean: Vec<f32>,
    pub z_r_logvar: Vec<f32>,
    pub z_e_mean: Vec<f32>,
    pub z_e_logvar: Vec<f32>,
    pub z_i_mean: Vec<f32>,
    pub z_i_logvar: Vec<f32>,
    /// How far the test-time yaw copies' headings scatter about the fused one (radians, RMS over
    /// every copy, outvoted ones included; `crate::yaw_copies`): None with a single copy. A frame
    /// whose copies disagree is one the encoder reads poorly (the heading tracker weighs it less).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub yaw_spread: Option<f32>,
}

impl Encoding {
    /// Every output value is finite (a NaN would poison the tracker's running estimates).
    pub fn is_finite(&self) -> bool {
        self.q.iter().all(|v| v.is_finite())
            && [
                &self.x_c,
                &self.z_r_mean,
                &self.z_r_logvar,
                &self.z_e_mean,
                &self.z_e_logvar,
                &self.z_i_mean,
                &self.z_i_logvar,
            ]
            .iter()
            .all(|values| values.iter().all(|v| v.is_finite()))
    }
}
