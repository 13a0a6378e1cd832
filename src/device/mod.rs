//! What a template means for one device on the bus: resolved channels and setup writes, and the
//! value codecs between register words and MQTT value strings.
// Located errors are built once per bad file, at load time: their size does not matter, and
// boxing them would only make every `match` on `problem` noisier.
#![allow(clippy::result_large_err)]

pub mod codec;
pub mod configure;
pub mod firmware;
pub mod merge;
pub mod model;
pub mod number_text;
pub mod resolve;

pub use crate::config::format::{ByteOrder, RegisterFormat, WordOrder};
pub use codec::{CodecError, Reading, ValueCodec};
pub use configure::{
    check_template, resolve_config, resolve_template_device, resolve_template_device_unconfigured,
    resolve_template_device_with_warnings,
};
pub use model::{
    ChannelRegister, DeviceTiming, EnumTitle, EventMode, Priority, RegisterRef, RegisterType,
    ResolvedChannel, ResolvedDevice, ResolvedPort, SetupItem, SharedVec, Titles, WriteFunction,
};
