//! What a template means for one device on the bus: resolved channels and setup writes, and the
//! value codecs between register words and MQTT value strings.

pub mod codec;
pub mod format;
pub mod number_text;

pub use codec::{CodecError, Reading, ValueCodec};
pub use format::{ByteOrder, RegisterFormat, WordOrder};
