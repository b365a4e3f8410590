//! A small CDR (OMG XCDR1, as ROS 2 serialises messages) reader and writer for the few message
//! types `homing` reads from and writes to ROS 2 bags: `std_msgs/msg/Header`,
//! `sensor_msgs/msg/Image` and `sensor_msgs/msg/CameraInfo`.
//!
//! A payload starts with a 4-byte encapsulation header (`00 01 00 00`: little endian,
//! `00 00 00 00`: big endian); every primitive is aligned to its own size, counted from the end
//! of that header. Strings are a `u32` length (with the terminating NUL) and the bytes;
//! sequences are a `u32` count and the elements; fixed arrays are the elements only.
//!
//! Hand-written because no maintained crate does just this: the `cdr` crate is a generic serde
//! format (the message structs would still have to be written, and its byte sequences go
//! element by element), and the ROS 2 interface crates bring every message package along.

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch (negative seconds clamp to 0).
    pub fn as_ns(&self) -> u64 {
        (self.sec.max(0) as u64) * 1_000_000_000 + self.nanosec as u64
    }
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: (ns / 1_000_000_000) as i32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/CameraInfo` (without the region of interest's use: it is read and kept).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    /// x_offset, y_offset, height, width.
    pub roi: [u32; 4],
    pub do_rectify: bool,
}

/// Why a payload could not be decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct CdrError(pub String);

impl std::fmt::Display for CdrError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

type R<T> = std::result::Result<T, CdrError>;

/// Reads a CDR payload.
pub struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
    le: bool,
}

impl<'a> Reader<'a> {
    /// Checks the encapsulation header and positions after it.
    pub fn new(payload: &'a [u8]) -> R<Self> {
        if payload.len() < 4 {
            return Err(CdrError(format!(
                "{} bytes: too short for a CDR payload",
                payload.len()
            )));
        }
        let le = match (payload[0], payload[1]) {
            (0, 1) => true,
            (0, 0) => false,
            (a, b) => {
                return Err(CdrError(format!(
                    "encapsulation {a:#04x}{b:02x} is not plain CDR (expected 0x0001 or 0x0000)"
                )));
            }
        };
        Ok(Self {
            buf: &payload[4..],
            pos: 0,
            le,
        })
    }

    fn align(&mut self, n: usize) {
        self.pos = self.pos.div_ceil(n) * n;
    }

    fn take(&mut self, n: usize, what: &str) -> R<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        let Some(end) = end else {
            return Err(CdrError(format!(
                "payload ends inside {what} (needs {n} bytes at offset {}, has {})",
                self.pos + 4,
                self.buf.len() + 4
            )));
        };
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn arr<const N: usize>(&mut self, what: &str) -> R<[u8; N]> {
        self.align(N);
        let s = self.take(N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        if !self.le {
            a.reverse();
        }
        Ok(a)
    }

    pub fn u8(&mut self, what: &str) -> R<u8> {
        Ok(self.take(1, what)?[0])
    }
    pub fn u32(&mut self, what: &str) -> R<u32> {
        self.arr::<4>(what).map(u32::from_le_bytes)
    }
    pub fn i32(&mut self, what: &str) -> R<i32> {
        self.arr::<4>(what).map(i32::from_le_bytes)
    }
    pub fn f64(&mut self, what: &str) -> R<f64> {
        self.arr::<8>(what).map(f64::from_le_bytes)
    }

    pub fn string(&mut self, what: &str) -> R<String> {
        let n = self.u32(what)? as usize;
        let s = self.take(n, what)?;
        let s = s.strip_suffix(&[0]).unwrap_or(s);
        String::from_utf8(s.to_vec()).map_err(|_| CdrError(format!("{what} is not UTF-8")))
    }

    pub fn bytes(&mut self, what: &str) -> R<&'a [u8]> {
        let n = self.u32(what)? as usize;
        self.take(n, what)
    }

    fn f64s<const N: usize>(&mut self, what: &str) -> R<[f64; N]> {
        let mut a = [0.0; N];
        for v in a.iter_mut() {
            *v = self.f64(what)?;
        }
        Ok(a)
    }

    pub fn header(&mut self) -> R<Header> {
        let sec = self.i32("header.stamp.sec")?;
        let nanosec = self.u32("header.stamp.nanosec")?;
        let frame_id = self.string("header.frame_id")?;
        Ok(Header {
            stamp: Time { sec, nanosec },
            frame_id,
        })
    }
}

/// Decodes a `sensor_msgs/msg/Image`. With `with_data: false` the pixel bytes are skipped
/// (only checked to be there), for scanning a bag.
pub fn decode_image(payload: &[u8], with_data: bool) -> R<Image> {
    let mut r = Reader::new(payload)?;
    let header = r.header()?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    let encoding = r.string("encoding")?;
    let is_bigendian = r.u8("is_bigendian")?;
    let step = r.u32("step")?;
    let data = r.bytes("data")?;
    Ok(Image {
        header,
        height,
        width,
        encoding,
        is_bigendian,
        step,
        data: if with_data { data.to_vec() } else { Vec::new() },
    })
}

/// Decodes a `sensor_msgs/msg/CameraInfo`.
pub fn decode_camera_info(payload: &[u8]) -> R<CameraInfo> {
    let mut r = Reader::new(payload)?;
    let header = r.header()?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    let distortion_model = r.string("distortion_model")?;
    let n = r.u32("d")? as usize;
    if n > 64 {
        return Err(CdrError(format!("d has {n} coefficients (corrupt?)")));
    }
    let mut d = Vec::with_capacity(n);
    for _ in 0..n {
        d.push(r.f64("d")?);
    }
    let k = r.f64s::<9>("k")?;
    let rr = r.f64s::<9>("r")?;
    let p = r.f64s::<12>("p")?;
    let binning_x = r.u32("binning_x")?;
    let binning_y = r.u32("binning_y")?;
    let roi = [
        r.u32("roi.x_offset")?,
        r.u32("roi.y_offset")?,
        r.u32("roi.height")?,
        r.u32("roi.width")?,
    ];
    let do_rectify = r.u8("roi.do_rectify")? != 0;
    Ok(CameraInfo {
        header,
        height,
        width,
        distortion_model,
        d,
        k,
        r: rr,
        p,
        binning_x,
        binning_y,
        roi,
        do_rectify,
    })
}

/// Writes a little-endian CDR payload.
pub struct Writer {
    buf: Vec<u8>,
}

impl Default for Writer {
    fn default() -> Self {
        Self::new()
    }
}

impl Writer {
    pub fn new() -> Self {
        Self {
            buf: vec![0, 1, 0, 0],
        }
    }
    fn align(&mut self, n: usize) {
        let pos = self.buf.len() - 4;
        let to = pos.div_ceil(n) * n;
        self.buf.resize(to + 4, 0);
    }
    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }
    pub fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.buf.extend_from_slice(b);
    }
    pub fn header(&mut self, h: &Header) {
        self.i32(h.stamp.sec);
        self.u32(h.stamp.nanosec);
        self.string(&h.frame_id);
    }
    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

pub fn encode_image(m: &Image) -> Vec<u8> {
    let mut w = Writer::new();
    w.header(&m.header);
    w.u32(m.height);
    w.u32(m.width);
    w.string(&m.encoding);
    w.u8(m.is_bigendian);
    w.u32(m.step);
    w.bytes(&m.data);
    w.finish()
}

pub fn encode_camera_info(m: &CameraInfo) -> Vec<u8> {
    let mut w = Writer::new();
    w.header(&m.header);
    w.u32(m.height);
    w.u32(m.width);
    w.string(&m.distortion_model);
    w.u32(m.d.len() as u32);
    m.d.iter().for_each(|&v| w.f64(v));
    m.k.iter().for_each(|&v| w.f64(v));
    m.r.iter().for_each(|&v| w.f64(v));
    m.p.iter().for_each(|&v| w.f64(v));
    w.u32(m.binning_x);
    w.u32(m.binning_y);
    m.roi.iter().for_each(|&v| w.u32(v));
    w.u8(u8::from(m.do_rectify));
    w.finish()
}

/// The ROS 2 message definitions (`ros2msg` schema encoding) of the types written.
pub const IMAGE_MSG: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";

pub const CAMERA_INFO_MSG: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n================================================================================\nMSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_round_trip_and_alignment() {
        let m = Image {
            header: Header {
                stamp: Time {
                    sec: 1305031102,
                    nanosec: 175304000,
                },
                frame_id: "cam".into(),
            },
            height: 2,
            width: 3,
            encoding: "rgb8".into(),
            is_bigendian: 0,
            step: 9,
            data: (0..18).collect(),
        };
        let b = encode_image(&m);
        // header(4) sec(4) nsec(4) frame_id len(4)+"cam\0"(4) height width; "rgb8\0" is 5 bytes,
        // so is_bigendian sits at 33 and step is aligned to 36 (CDR aligns relative to the payload,
        // after the 4-byte encapsulation header).
        assert_eq!(&b[..4], &[0, 1, 0, 0]);
        assert_eq!(b[4 + 33], 0);
        assert_eq!(u32::from_le_bytes(b[4 + 36..4 + 40].try_into().unwrap()), 9);
        assert_eq!(decode_image(&b, true).unwrap(), m);
        // Truncated payloads are errors, not panics.
        for n in 0..b.len() {
            assert!(decode_image(&b[..n], true).is_err());
        }
    }

    #[test]
    fn camera_info_round_trip() {
        let mut m = CameraInfo {
            distortion_model: "plumb_bob".into(),
            d: vec![0.1, -0.2, 0.0, 0.0, 0.3],
            width: 640,
            height: 480,
            ..Default::default()
        };
        m.k = [517.3, 0.0, 318.6, 0.0, 516.5, 255.3, 0.0, 0.0, 1.0];
        let b = encode_camera_info(&m);
        assert_eq!(decode_camera_info(&b).unwrap(), m);
        m.d.clear();
        let b = encode_camera_info(&m);
        assert_eq!(decode_camera_info(&b).unwrap(), m);
    }
}
