//! ROS 2 messages in CDR: `sensor_msgs/msg/PointCloud2` with any field layout and point step, and
//! `sensor_msgs/msg/Image` (16UC1 / 32FC1 depth) unprojected through `sensor_msgs/msg/CameraInfo`.
//!
//! Everything is bounds-checked: a truncated or hostile payload (a header claiming billions of
//! points, a string longer than the message) is an error naming the field, never a panic or a huge
//! allocation.

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CdrError {
    #[error("payload too short for the CDR encapsulation header")]
    NoHeader,
    #[error("unsupported CDR representation {0:#06x} (expected CDR_LE 0x0001 or CDR_BE 0x0000)")]
    Representation(u16),
    #[error("truncated while reading {0}")]
    Truncated(&'static str),
    #[error("{0}")]
    Invalid(String),
}

/// A CDR stream; alignment is relative to the end of the 4-byte encapsulation header.
struct Cdr<'a> {
    data: &'a [u8],
    position: usize,
    little: bool,
}

impl<'a> Cdr<'a> {
    fn new(payload: &'a [u8]) -> Result<Self, CdrError> {
        if payload.len() < 4 {
            return Err(CdrError::NoHeader);
        }
        let representation = u16::from_be_bytes([payload[0], payload[1]]);
        let little = match representation {
            0x0001 | 0x0003 => true,
            0x0000 | 0x0002 => false,
            other => return Err(CdrError::Representation(other)),
        };
        Ok(Self {
            data: &payload[4..],
            position: 0,
            little,
        })
    }

    fn align(&mut self, n: usize) {
        self.position = self.position.div_ceil(n) * n;
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        let end = self.position.checked_add(n).ok_or(CdrError::Truncated(what))?;
        let slice = self.data.get(self.position..end).ok_or(CdrError::Truncated(what))?;
        self.position = end;
        Ok(slice)
    }

    fn u8(&mut self, what: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(1, what)?[0])
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, CdrError> {
        self.align(4);
        let b: [u8; 4] = self.take(4, what)?.try_into().unwrap();
        Ok(if self.little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    fn i32(&mut self, what: &'static str) -> Result<i32, CdrError> {
        Ok(self.u32(what)? as i32)
    }

    fn f64(&mut self, what: &'static str) -> Result<f64, CdrError> {
        self.align(8);
        let b: [u8; 8] = self.take(8, what)?.try_into().unwrap();
        Ok(if self.little {
            f64::from_le_bytes(b)
        } else {
            f64::from_be_bytes(b)
        })
    }

    fn string(&mut self, what: &'static str) -> Result<String, CdrError> {
        let length = self.u32(what)? as usize;
        let bytes = self.take(length, what)?;
        let text = bytes.strip_suffix(&[0]).unwrap_or(bytes);
        Ok(String::from_utf8_lossy(text).into_owned())
    }

    fn bytes(&mut self, what: &'static str) -> Result<&'a [u8], CdrError> {
        let length = self.u32(what)? as usize;
        self.take(length, what)
    }

    fn header(&mut self) -> Result<Header, CdrError> {
        let sec = self.i32("header.stamp.sec")?;
        let nanosec = self.u32("header.stamp.nanosec")?;
        let frame_id = self.string("header.frame_id")?;
        Ok(Header {
            stamp_ns: (sec.max(0) as u64) * 1_000_000_000 + nanosec as u64,
            frame_id,
        })
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    pub stamp_ns: u64,
    pub frame_id: String,
}

/// A decoded cloud: finite x, y, z of every point, and how many non-finite points were dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedCloud {
    pub header: Header,
    pub points: Vec<[f32; 3]>,
    pub dropped_non_finite: usize,
}

/// PointField datatypes.
fn datatype_size(datatype: u8) -> Option<usize> {
    match datatype {
        1 | 2 => Some(1),
        3 | 4 => Some(2),
        5..=7 => Some(4),
        8 => Some(8),
        _ => None,
    }
}

fn read_scalar(bytes: &[u8], datatype: u8, big_endian: bool) -> f64 {
    macro_rules! num {
        ($t:ty, $n:expr) => {{
            let b: [u8; $n] = bytes[..$n].try_into().unwrap();
            (if big_endian {
                <$t>::from_be_bytes(b)
            } else {
                <$t>::from_le_bytes(b)
            }) as f64
        }};
    }
    match datatype {
        1 => bytes[0] as i8 as f64,
        2 => bytes[0] as f64,
        3 => num!(i16, 2),
        4 => num!(u16, 2),
        5 => num!(i32, 4),
        6 => num!(u32, 4),
        7 => num!(f32, 4),
        _ => num!(f64, 8),
    }
}

/// Decodes a CDR `sensor_msgs/msg/PointCloud2`, taking x, y and z wherever the fields put them.
pub fn decode_point_cloud2(payload: &[u8], max_points: usize) -> Result<DecodedCloud, CdrError> {
    let mut cdr = Cdr::new(payload)?;
    let header = cdr.header()?;
    let height = cdr.u32("height")? as usize;
    let width = cdr.u32("width")? as usize;
    let field_count = cdr.u32("fields length")? as usize;
    if field_count > 1024 {
        return Err(CdrError::Invalid(format!("{field_count} fields")));
    }
    let mut axes: [Option<(usize, u8)>; 3] = [None; 3];
    for _ in 0..field_count {
        let name = cdr.string("field name")?;
        let offset = cdr.u32("field offset")? as usize;
        let datatype = cdr.u8("field datatype")?;
        let _count = cdr.u32("field count")?;
        let axis = match name.as_str() {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            _ => continue,
        };
        if datatype_size(datatype).is_none() {
            return Err(CdrError::Invalid(format!(
                "field '{name}' has unknown datatype {datatype}"
            )));
        }
        axes[axis] = Some((offset, datatype));
    }
    let [Some(x), Some(y), Some(z)] = axes else {
        return Err(CdrError::Invalid("the cloud has no x, y and z fields".into()));
    };
    let big_endian = cdr.u8("is_bigendian")? != 0;
    let point_step = cdr.u32("point_step")? as usize;
    let row_step = cdr.u32("row_step")? as usize;
    let data = cdr.bytes("data")?;
    let points = height
        .checked_mul(width)
        .filter(|&n| n <= max_points)
        .ok_or_else(|| CdrError::Invalid(format!("{height} x {width} points (more than {max_points})")))?;
    for (offset, datatype) in [x, y, z] {
        if offset + datatype_size(datatype).unwrap() > point_step {
            return Err(CdrError::Invalid(format!(
                "a field at offset {offset} overruns point_step {point_step}"
            )));
        }
    }
    if row_step < width * point_step || data.len() < height.saturating_sub(1) * row_step + width * point_step {
        return Err(CdrError::Invalid(format!(
            "data has {} bytes; {height} rows of {width} points x {point_step} bytes (row_step {row_step}) do not fit",
            data.len()
        )));
    }
    let mut decoded = Vec::with_capacity(points);
    // The common layout (little-endian float32 x, y, z) is read straight from the message's
    // bytes, with no per-value dispatch; rows and points are walked as slices of the data.
    let fast = !big_endian && [x, y, z].iter().all(|(_, datatype)| *datatype == 7);
    let float = |point: &[u8], o: usize| f32::from_le_bytes(point[o..o + 4].try_into().expect("4 bytes"));
    let value =
        |point: &[u8], (offset, datatype): (usize, u8)| read_scalar(&point[offset..], datatype, big_endian) as f32;
    for row in 0..height {
        let row = &data[row * row_step..row * row_step + width * point_step];
        for point in row.chunks_exact(point_step) {
            let p = if fast {
                [float(point, x.0), float(point, y.0), float(point, z.0)]
            } else {
                [value(point, x), value(point, y), value(point, z)]
            };
            if p.iter().all(|c| c.is_finite()) {
                decoded.push(p);
            }
        }
    }
    let dropped = points - decoded.len();
    Ok(DecodedCloud {
        header,
        points: decoded,
        dropped_non_finite: dropped,
    })
}

/// Pinhole intrinsics from a CameraInfo (`k` of a rectified image).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraIntrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

pub fn decode_camera_info(payload: &[u8]) -> Result<(Header, CameraIntrinsics), CdrError> {
    let mut cdr = Cdr::new(payload)?;
    let header = cdr.header()?;
    let height = cdr.u32("height")?;
    let width = cdr.u32("width")?;
    let _model = cdr.string("distortion_model")?;
    let d = cdr.u32("d length")? as usize;
    if d > 64 {
        return Err(CdrError::Invalid(format!("{d} distortion coefficients")));
    }
    for _ in 0..d {
        cdr.f64("d")?;
    }
    let mut k = [0.0; 9];
    for value in &mut k {
        *value = cdr.f64("k")?;
    }
    let intrinsics = CameraIntrinsics {
        width,
        height,
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
    };
    if !(intrinsics.fx > 0.0 && intrinsics.fy > 0.0 && intrinsics.fx.is_finite() && intrinsics.fy.is_finite())
        || !(intrinsics.cx.is_finite() && intrinsics.cy.is_finite())
    {
        return Err(CdrError::Invalid(format!(
            "camera matrix has fx = {}, fy = {}, cx = {}, cy = {}",
            k[0], k[4], k[2], k[5]
        )));
    }
    Ok((header, intrinsics))
}

/// Decodes a depth `Image` (16UC1 millimetres or 32FC1 metres) and unprojects its valid pixels
/// (optical frame, metres), keeping every `step`-th pixel in each direction.
pub fn decode_depth_image(
    payload: &[u8],
    intrinsics: &CameraIntrinsics,
    step: usize,
    max_points: usize,
) -> Result<DecodedCloud, CdrError> {
    let mut cdr = Cdr::new(payload)?;
    let header = cdr.header()?;
    let height = cdr.u32("height")? as usize;
    let width = cdr.u32("width")? as usize;
    let encoding = cdr.string("encoding")?;
    let big_endian = cdr.u8("is_bigendian")? != 0;
    let row_step = cdr.u32("step")? as usize;
    let data = cdr.bytes("data")?;
    let (pixel, scale, datatype) = match encoding.as_str() {
        "16UC1" | "mono16" => (2, 0.001, 4u8),
        "32FC1" => (4, 1.0, 7u8),
        other => {
            return Err(CdrError::Invalid(format!(
                "depth encoding '{other}' (supported: 16UC1, 32FC1)"
            )))
        }
    };
    if width == 0 || height == 0 || row_step == 0 {
        return Err(CdrError::Invalid(format!(
            "empty image: {width} x {height}, row step {row_step}"
        )));
    }
    if width.saturating_mul(height) > max_points.saturating_mul(step.max(1) * step.max(1)) {
        return Err(CdrError::Invalid(format!("{width} x {height} image is too large")));
    }
    if row_step < width * pixel || data.len() < height.saturating_sub(1) * row_step + width * pixel {
        return Err(CdrError::Invalid(format!(
            "image data of {} bytes does not hold {height} rows of {row_step} bytes",
            data.len()
        )));
    }
    if width as u32 != intrinsics.width || height as u32 != intrinsics.height {
        return Err(CdrError::Invalid(format!(
            "image is {width}x{height} but its CameraInfo is {}x{}",
            intrinsics.width, intrinsics.height
        )));
    }
    let step = step.max(1);
    let mut points = Vec::new();
    for v in (0..height).step_by(step) {
        for u in (0..width).step_by(step) {
            let start = v * row_step + u * pixel;
            let depth = read_scalar(&data[start..start + pixel], datatype, big_endian) * scale;
            if depth.is_finite() && depth > 0.0 {
                let x = (u as f64 - intrinsics.cx) / intrinsics.fx * depth;
                let y = (v as f64 - intrinsics.cy) / intrinsics.fy * depth;
                points.push([x as f32, y as f32, depth as f32]);
            }
        }
    }
    Ok(DecodedCloud {
        header,
        points,
        dropped_non_finite: 0,
    })
}
