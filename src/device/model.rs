//! The resolved, flat view of a configured device: what the daemon polls and publishes, and what
//! the simulator builds its virtual registers from. Templates, config overrides, subdevices,
//! parameters and conditions are all applied; nothing here needs the JSON any more.

use std::sync::Arc;
use std::time::Duration;

use super::codec::{CodecError, Reading, ValueCodec};
use crate::config::config_file::PortConfig;
use crate::config::template::HardwareSignature;

/// Modbus data table: the protocol core's type, so a channel's registers go to the bus as they are.
pub use crate::protocol::RegisterType;

/// Which write function a holding register needs (`holding_single`, `holding_multi`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WriteFunction {
    /// 05 for a coil, 06 for one register, 16 for several.
    #[default]
    Auto,
    /// Always 06; a multi-register value is written as separate 06 writes.
    Single,
    /// Always 16, even for one register.
    Multiple,
}

/// A span of one data table: `count` registers (or bits) from `address`, with the value's bit
/// field inside them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct RegisterRef {
    pub reg_type: RegisterType,
    pub address: u16,
    /// 16-bit registers, or bits for coils and discrete inputs.
    pub count: u16,
    pub bit_shift: u32,
    pub bit_width: u32,
}

impl RegisterRef {
    /// The registers (or bits) it covers, as the port scheduler reads them; the bit field
    /// inside them is the codec's business.
    pub fn span(&self) -> crate::port::RegisterSpan {
        crate::port::RegisterSpan::new(self.reg_type, self.address, self.count.max(1))
    }

    /// Last address covered (inclusive).
    pub fn last_address(&self) -> u16 {
        self.address.saturating_add(self.count.saturating_sub(1))
    }
}

/// How a channel's registers are kept up to date (template `sporadic`, `semi-sporadic`): the
/// port scheduler's type, so a channel's mode goes to the bus as it is.
pub use crate::port::EventMode;

/// Polling / event priority: channels with `read_period_ms` are high priority.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Default)]
pub enum Priority {
    #[default]
    Low,
    High,
}

/// One register value of a channel (most channels have one; `consists_of` gives several).
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelRegister {
    /// Where the value is read; None for write-only channels.
    pub read: Option<RegisterRef>,
    /// Where it is written; None when read-only.
    pub write: Option<RegisterRef>,
    pub write_function: WriteFunction,
    pub codec: ValueCodec,
    /// WB press counter: a 0 read right after a reboot is not published.
    pub press_counter: bool,
}

/// A text per language, sorted by language code (as the meta JSON lists them). A channel has
/// one to three languages: a short list, where a map would allocate a whole tree node (over
/// 500 bytes) for every channel and enum value.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Titles(Vec<(String, String)>);

impl Titles {
    pub fn get(&self, lang: &str) -> Option<&String> {
        self.position(lang).ok().map(|i| &self.0[i].1)
    }

    /// Sets the text of `lang`, replacing any it had.
    pub fn insert(&mut self, lang: String, text: String) {
        match self.position(&lang) {
            Ok(i) => self.0[i].1 = text,
            Err(i) => self.0.insert(i, (lang, text)),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    pub fn len(&self) -> usize {
        self.0.len()
    }

    pub fn clear(&mut self) {
        self.0.clear();
    }

    /// (language, text), by language.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &str)> {
        self.0
            .iter()
            .map(|(lang, text)| (lang.as_str(), text.as_str()))
    }

    fn position(&self, lang: &str) -> Result<usize, usize> {
        self.0.binary_search_by(|(key, _)| key.as_str().cmp(lang))
    }
}

impl FromIterator<(String, String)> for Titles {
    fn from_iter<I: IntoIterator<Item = (String, String)>>(items: I) -> Self {
        let mut titles = Titles::default();
        for (lang, text) in items {
            titles.insert(lang, text);
        }
        titles.0.shrink_to_fit();
        titles
    }
}

impl<const N: usize> From<[(String, String); N]> for Titles {
    fn from(items: [(String, String); N]) -> Self {
        items.into_iter().collect()
    }
}

/// A JSON object `{lang: text}`, as the meta's `title` and `enum` carry it.
impl serde::Serialize for Titles {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_map(self.iter())
    }
}

/// Title of one enum value, per language.
#[derive(Debug, Clone, PartialEq)]
pub struct EnumTitle {
    pub value: String,
    pub title: Titles,
}

/// One MQTT control.
#[derive(Debug, Clone, PartialEq)]
pub struct ResolvedChannel {
    /// MQTT control id (`/devices/<dev>/controls/<id>`).
    pub id: String,
    /// Template name (with subdevice prefixes): what config overrides match.
    pub name: String,
    /// Title per language for the control meta.
    pub title: Titles,
    pub registers: Vec<ChannelRegister>,
    /// WB control type (`value`, `switch`, `range`, `text`, `pushbutton`, `rgb`, deprecated
    /// typed values …); `wo-switch` is already turned into a write-only `switch`.
    pub control_type: String,
    pub units: Option<String>,
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// `round_to`, published as meta `precision`.
    pub precision: Option<f64>,
    pub readonly: bool,
    /// No register to read (pushbutton, wo-switch, only `write_address`).
    pub write_only: bool,
    /// 1-based position in the device, meta `order`.
    pub order: u32,
    pub enum_titles: Vec<EnumTitle>,
    pub events: EventMode,
    pub read_period: Option<Duration>,
    pub read_rate_limit: Option<Duration>,
    /// Minimum WB firmware; older devices get `r` for this channel and do not poll it.
    pub fw: Option<String>,
    pub hidden: bool,
    pub group: Option<String>,
}

/// A decoded channel value.
pub type ChannelReading = Reading;

impl ResolvedChannel {
    /// Some register of it is read: the controls a device that does not answer flags `r`.
    pub fn is_read(&self) -> bool {
        self.registers.iter().any(|r| r.read.is_some())
    }

    /// Priority of polling and of the 0x18 event enable record.
    pub fn priority(&self) -> Priority {
        if self.read_period.is_some() {
            Priority::High
        } else {
            Priority::Low
        }
    }

    /// Decodes the words of every register (in `registers` order) into the published text;
    /// several registers are joined with `;`.
    pub fn decode(&self, words: &[&[u16]]) -> Result<ChannelReading, CodecError> {
        if words.len() != self.registers.len() {
            return Err(CodecError::WordCount {
                expected: self.registers.len(),
                got: words.len(),
            });
        }
        let mut parts = Vec::with_capacity(words.len());
        for (register, part) in self.registers.iter().zip(words) {
            match register.codec.decode(part)? {
                Reading::Value(text) => parts.push(text),
                other => return Ok(other),
            }
        }
        Ok(Reading::Value(parts.join(";")))
    }

    /// Encodes an `/on` payload into the words to write, per register. `current` gives the
    /// present words of registers that are bit fields (None where unknown). Values outside
    /// the channel's `min`/`max` are refused.
    pub fn encode(
        &self,
        text: &str,
        current: &[Option<&[u16]>],
    ) -> Result<Vec<Vec<u16>>, CodecError> {
        let parts: Vec<&str> = if self.registers.len() > 1 {
            text.split(';').collect()
        } else {
            vec![text]
        };
        if parts.len() != self.registers.len() {
            return Err(CodecError::WordCount {
                expected: self.registers.len(),
                got: parts.len(),
            });
        }
        let mut out = Vec::with_capacity(parts.len());
        for (i, (register, part)) in self.registers.iter().zip(parts).enumerate() {
            self.check_limits(part.trim())?;
            out.push(
                register
                    .codec
                    .encode(part, current.get(i).copied().flatten())?,
            );
        }
        Ok(out)
    }

    fn check_limits(&self, text: &str) -> Result<(), CodecError> {
        // An integer in hex (`0x64`) is held to the limits as well.
        let value = match crate::config::values::parse_int_text(text) {
            Some(integer) => integer as f64,
            None => match text.parse::<f64>() {
                Ok(value) => value,
                Err(_) => return Ok(()),
            },
        };
        let below = self.min.is_some_and(|min| value < min);
        let above = self.max.is_some_and(|max| value > max);
        if below || above {
            let show = |v: f64| super::number_text::format_g(v, 15);
            let limits = match (self.min, self.max) {
                (Some(min), Some(max)) => format!("allowed {} … {}", show(min), show(max)),
                (Some(min), None) => format!("at least {}", show(min)),
                (None, Some(max)) => format!("at most {}", show(max)),
                (None, None) => String::new(),
            };
            return Err(CodecError::OutsideLimits {
                value: text.to_string(),
                limits,
            });
        }
        Ok(())
    }
}

/// A setup item of the template or a parameter value: written when the device (re)connects, as
/// the port scheduler's [`crate::port::SetupWrite`] (its holding-register words).
#[derive(Debug, Clone, PartialEq)]
pub struct SetupItem {
    pub title: String,
    pub register: RegisterRef,
    pub write_function: WriteFunction,
    /// The value as configured (for logs).
    pub value: String,
    /// Encoded words: for a bit field, over what the setup items before it wrote to the
    /// register (zeros elsewhere).
    pub words: Vec<u16>,
    /// Per word, the bits no setup item up to this one defines (none for a whole-register
    /// value): taken from the register's last read contents when there are some, as
    /// wb-mqtt-serial composes setup writes over its register cache.
    pub kept_bits: Vec<u16>,
    pub codec: ValueCodec,
    /// Set when the write comes from a template parameter.
    pub parameter_id: Option<String>,
}

/// Link timings and limits of a device, with the port's values and the defaults applied.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceTiming {
    pub response_timeout: Duration,
    pub frame_timeout: Duration,
    pub force_frame_timeout: bool,
    pub guard_interval: Duration,
    pub min_request_interval: Duration,
    /// None: never disconnect on time (-1).
    pub device_timeout: Option<Duration>,
    pub device_max_fail_cycles: Option<u32>,
    pub max_write_fail_time: Duration,
    /// 0 = protocol maximum.
    pub max_read_registers: u16,
    pub min_read_registers: u16,
    pub max_write_registers: u16,
    pub max_reg_hole: u16,
    pub max_bit_hole: u16,
    pub enable_wb_continuous_read: bool,
    pub continue_polling_on_illegal_modbus_exception: bool,
    pub read_rate_limit: Option<Duration>,
}

/// A list resolved once and shared by every device made from the same template with the same
/// overrides (channels, setup items): a device's own memory is then its address, id and name,
/// not a copy of its template. Reads as a slice; tests that build variants call
/// [`SharedVec::make_mut`], which copies the list first if another device shares it.
#[derive(Clone)]
pub struct SharedVec<T>(Arc<Vec<T>>);

impl<T> SharedVec<T> {
    /// Shares `items`, without the spare capacity left by building them.
    pub fn new(mut items: Vec<T>) -> Self {
        items.shrink_to_fit();
        Self(Arc::new(items))
    }

    /// Whether `a` and `b` are the same list in memory (not merely equal).
    pub fn ptr_eq(a: &Self, b: &Self) -> bool {
        Arc::ptr_eq(&a.0, &b.0)
    }
}

impl<T: Clone> SharedVec<T> {
    /// The list to change, copied first when other devices share it.
    pub fn make_mut(&mut self) -> &mut Vec<T> {
        Arc::make_mut(&mut self.0)
    }
}

impl<T> Default for SharedVec<T> {
    fn default() -> Self {
        Self(Arc::new(Vec::new()))
    }
}

impl<T> std::ops::Deref for SharedVec<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        &self.0
    }
}

impl<'a, T> IntoIterator for &'a SharedVec<T> {
    type Item = &'a T;
    type IntoIter = std::slice::Iter<'a, T>;
    fn into_iter(self) -> Self::IntoIter {
        self.0.iter()
    }
}

impl<T> From<Vec<T>> for SharedVec<T> {
    fn from(items: Vec<T>) -> Self {
        Self::new(items)
    }
}

impl<T: PartialEq> PartialEq for SharedVec<T> {
    fn eq(&self, other: &Self) -> bool {
        Self::ptr_eq(self, other) || self.0 == other.0
    }
}

impl<T: std::fmt::Debug> std::fmt::Debug for SharedVec<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

/// One configured device, ready to poll.
#[derive(Debug, Clone, PartialEq)]
pub struct ResolvedDevice {
    /// MQTT device id.
    pub id: String,
    /// Device title.
    pub name: String,
    pub device_type: Option<String>,
    pub slave_id: u8,
    /// A WBIO module behind a WB-MIO (`modbus_io`, `slave_id` "address:module"): its registers
    /// are shifted from the host's at `slave_id`.
    pub modbus_io: bool,
    /// WB device (template has `hw` or continuous read): WB-specific behaviour applies.
    pub is_wb: bool,
    pub hw: Vec<HardwareSignature>,
    pub timing: DeviceTiming,
    /// Shared with the other devices of the same template and overrides.
    pub channels: SharedVec<ResolvedChannel>,
    /// In write order; shared like `channels`.
    pub setup: SharedVec<SetupItem>,
    /// Register of the serial number (channels `Serial`, `serial_number`, `Serial NO`), even
    /// when that channel is disabled: used by scan and probe to match devices.
    pub serial_number: Option<ChannelRegister>,
}

impl ResolvedDevice {
    /// The `read_rate_limit_ms` in force for one of its channels: the channel's own, else the
    /// device's (itself else the port's), as wb-mqtt-serial; zero limits nothing.
    pub fn read_rate_limit(&self, channel: &ResolvedChannel) -> Option<Duration> {
        channel
            .read_rate_limit
            .or(self.timing.read_rate_limit)
            .filter(|limit| !limit.is_zero())
    }

    /// All enabled channels use events only (`sporadic`): one of them is kept in polling to
    /// notice a lost device.
    pub fn is_sporadic_only(&self) -> bool {
        !self.channels.is_empty()
            && self
                .channels
                .iter()
                .all(|c| c.events == EventMode::Sporadic)
    }

    pub fn channel(&self, id: &str) -> Option<&ResolvedChannel> {
        self.channels.iter().find(|c| c.id == id)
    }
}

/// One port with its resolved devices.
#[derive(Debug, Clone)]
pub struct ResolvedPort {
    /// Index in the config's `ports`.
    pub index: usize,
    pub config: PortConfig,
    pub devices: Vec<ResolvedDevice>,
    /// This port's share of the config's `rate_limit` (low-priority channel reads per second),
    /// in proportion to its channels; `None`: no limit.
    pub low_priority_read_limit: Option<u32>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Titles keep one text per language, sorted by language code whatever the order they
    /// came in, and serialize as the JSON object the meta carries.
    #[test]
    fn titles_are_one_text_per_language_in_order() {
        let mut titles = Titles::from([
            ("ru".to_string(), "Температура".to_string()),
            ("en".to_string(), "Temp".to_string()),
        ]);
        titles.insert("en".into(), "Temperature".into());
        titles.insert("de".into(), "Temperatur".into());
        assert_eq!(titles.len(), 3);
        assert_eq!(titles.get("en").map(String::as_str), Some("Temperature"));
        assert_eq!(titles.get("fr"), None);
        assert_eq!(
            serde_json::to_string(&titles).unwrap(),
            r#"{"de":"Temperatur","en":"Temperature","ru":"Температура"}"#
        );
    }

    #[test]
    fn shared_lists_compare_by_content_and_copy_on_change() {
        let a = SharedVec::new(vec![1, 2, 3]);
        let mut b = a.clone();
        assert!(SharedVec::ptr_eq(&a, &b));
        b.make_mut().push(4);
        assert!(!SharedVec::ptr_eq(&a, &b));
        assert_eq!(&a[..], [1, 2, 3]);
        assert_eq!(&b[..], [1, 2, 3, 4]);
        assert_eq!(SharedVec::new(vec![1, 2, 3]), a);
    }
}
