//! A serial port's receive FIFO, as the kernel reports it, and lowering its trigger level for a
//! site tool's run.
//!
//! A 16550-style UART hands received bytes over when its FIFO holds `rx_trig_bytes` of them, or
//! once the line has been quiet for its receive timeout. Linux sets the trigger to 8 bytes on a
//! 16550A (half the FIFO on wider ones). A reply's first byte can then reach the reader several
//! characters late, and the filler bytes of a Fast Modbus arbitration, which come a window apart
//! and never leave the line quiet for long, may not reach it before the winner's whole frame is
//! in: a master that ends a scan setting when the first window brought nothing would miss every
//! device. The exchange allows for the trigger level ([`super::exchange::FirstByteHold`]), but
//! every allowance costs bus time, so the trigger is lowered to 1 byte where the kernel allows
//! it: by `rtu2mqtt prepare-ports` (the service runs it as root) and by the daemon when it opens
//! a port, as wb-mqtt-serial does (it is left so), and by a site tool for its run only (put back
//! when it ends).
//!
//! The kernel shows the attribute for 8250-family ports only; USB adapters and pseudo-terminals
//! have none (a USB adapter's latency timer is its own allowance, see `tools::adapter`).

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use tracing::debug;

/// The sysfs directory of tty devices on this machine.
pub fn sysfs_tty() -> PathBuf {
    PathBuf::from("/sys/class/tty")
}

/// The sysfs directory of the tty at `path` (`<sysfs_tty>/<name>`; symbolic links such as
/// `/dev/ttyRS485-1` are followed to the device node).
pub fn tty_dir(path: &Path, sysfs_tty: &Path) -> Option<PathBuf> {
    let node = fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    Some(sysfs_tty.join(node.file_name()?))
}

/// A number from a sysfs attribute.
pub fn read_number<T: std::str::FromStr>(attribute: &Path) -> Option<T> {
    fs::read_to_string(attribute).ok()?.trim().parse().ok()
}

/// The `rx_trig_bytes` attribute of the port at `path`, if the kernel has one for it.
fn trigger_attribute(path: &Path, sysfs_tty: &Path) -> Option<PathBuf> {
    let attribute = tty_dir(path, sysfs_tty)?.join("rx_trig_bytes");
    attribute.is_file().then_some(attribute)
}

/// How many bytes the port's receive FIFO collects before it hands them over, as the kernel
/// reports it; `None` when it does not say (USB adapters, pseudo-terminals).
pub fn receive_fifo_trigger(path: &Path, sysfs_tty: &Path) -> Option<u32> {
    trigger_attribute(path, sysfs_tty).and_then(|attribute| read_number::<u32>(&attribute))
}

/// What lowering a port's receive FIFO trigger to 1 byte did.
#[derive(Debug)]
pub enum TriggerChange {
    /// The kernel reports no trigger for the port (USB adapters, pseudo-terminals).
    NotReported,
    /// It was 1 byte already.
    AlreadyOne,
    /// Lowered from `previous` bytes.
    Lowered { attribute: PathBuf, previous: u32 },
    /// It collects this many bytes and could not be lowered (not root, or the driver refused).
    Holds { trigger: u32, why: io::Error },
}

/// Sets the port's receive FIFO trigger to 1 byte when it is higher, so that bytes reach the
/// reader as they come.
pub fn lower_to_one_byte(path: &Path, sysfs_tty: &Path) -> TriggerChange {
    let Some(attribute) = trigger_attribute(path, sysfs_tty) else {
        return TriggerChange::NotReported;
    };
    let Some(trigger) = read_number::<u32>(&attribute) else {
        return TriggerChange::NotReported;
    };
    if trigger <= 1 {
        return TriggerChange::AlreadyOne;
    }
    let lowered = fs::write(&attribute, "1").and_then(|()| match read_number::<u32>(&attribute) {
        Some(1) => Ok(()),
        other => Err(io::Error::other(format!(
            "the driver kept {} bytes",
            other.map_or_else(|| "?".to_owned(), |t| t.to_string())
        ))),
    });
    match lowered {
        Ok(()) => TriggerChange::Lowered {
            attribute,
            previous: trigger,
        },
        Err(why) => TriggerChange::Holds { trigger, why },
    }
}

/// What became of a port's receive FIFO for a tool's run.
#[derive(Debug)]
pub enum FifoForTool {
    /// The kernel reports no FIFO trigger, or it is already 1 byte.
    AsItIs,
    /// Lowered to 1 byte; put back to the old trigger when this is dropped.
    Lowered(LoweredTrigger),
    /// It collects this many bytes and could not be lowered (not root, or the driver refused).
    Holds { trigger: u32, why: io::Error },
}

/// A receive FIFO trigger lowered to 1 byte, put back on drop.
#[derive(Debug)]
pub struct LoweredTrigger {
    attribute: PathBuf,
    pub previous: u32,
}

impl Drop for LoweredTrigger {
    fn drop(&mut self) {
        if let Err(err) = fs::write(&self.attribute, self.previous.to_string()) {
            debug!(attribute = %self.attribute.display(), %err,
                "could not put the receive FIFO trigger back");
        }
    }
}

/// Lowers the port's receive FIFO trigger to 1 byte for a tool's run (see
/// [`lower_to_one_byte`]); the returned guard puts it back.
pub fn lower_for_tool(path: &Path, sysfs_tty: &Path) -> FifoForTool {
    match lower_to_one_byte(path, sysfs_tty) {
        TriggerChange::NotReported | TriggerChange::AlreadyOne => FifoForTool::AsItIs,
        TriggerChange::Lowered {
            attribute,
            previous,
        } => FifoForTool::Lowered(LoweredTrigger {
            attribute,
            previous,
        }),
        TriggerChange::Holds { trigger, why } => FifoForTool::Holds { trigger, why },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;

    /// A fake `/sys/class/tty` with `name`'s `rx_trig_bytes` set to `trigger`, and a `/dev`
    /// node with a symbolic link to it.
    fn fake_port(root: &Path, name: &str, trigger: Option<&str>) -> (PathBuf, PathBuf) {
        let sysfs = root.join("sys/class/tty");
        fs::create_dir_all(sysfs.join(name)).unwrap();
        if let Some(trigger) = trigger {
            fs::write(sysfs.join(name).join("rx_trig_bytes"), trigger).unwrap();
        }
        let dev = root.join("dev");
        fs::create_dir_all(&dev).unwrap();
        fs::write(dev.join(name), "").unwrap();
        symlink(dev.join(name), dev.join("ttyRS485-1")).unwrap();
        (dev.join("ttyRS485-1"), sysfs)
    }

    #[test]
    fn the_trigger_is_read_through_the_ports_symbolic_link() {
        let root = tempfile::tempdir().unwrap();
        let (port, sysfs) = fake_port(root.path(), "ttyS1", Some("8\n"));
        assert_eq!(receive_fifo_trigger(&port, &sysfs), Some(8));
        let (other, sysfs) = fake_port(&root.path().join("b"), "ttyUSB0", None);
        assert_eq!(receive_fifo_trigger(&other, &sysfs), None);
    }

    #[test]
    fn a_tool_lowers_the_trigger_to_one_byte_and_puts_it_back() {
        let root = tempfile::tempdir().unwrap();
        let (port, sysfs) = fake_port(root.path(), "ttyS1", Some("8"));
        let attribute = sysfs.join("ttyS1/rx_trig_bytes");
        let fifo = lower_for_tool(&port, &sysfs);
        let FifoForTool::Lowered(lowered) = &fifo else {
            panic!("not lowered: {fifo:?}");
        };
        assert_eq!(lowered.previous, 8);
        assert_eq!(fs::read_to_string(&attribute).unwrap(), "1");
        assert_eq!(receive_fifo_trigger(&port, &sysfs), Some(1));
        drop(fifo);
        assert_eq!(fs::read_to_string(&attribute).unwrap(), "8");
    }

    #[test]
    fn lowered_to_one_byte_it_stays_so() {
        let root = tempfile::tempdir().unwrap();
        let (port, sysfs) = fake_port(root.path(), "ttyS1", Some("8\n"));
        let change = lower_to_one_byte(&port, &sysfs);
        assert!(
            matches!(change, TriggerChange::Lowered { previous: 8, .. }),
            "{change:?}"
        );
        drop(change);
        assert_eq!(receive_fifo_trigger(&port, &sysfs), Some(1));
        let again = lower_to_one_byte(&port, &sysfs);
        assert!(matches!(again, TriggerChange::AlreadyOne), "{again:?}");
        let (pty, sysfs) = fake_port(&root.path().join("b"), "pts3", None);
        let none = lower_to_one_byte(&pty, &sysfs);
        assert!(matches!(none, TriggerChange::NotReported), "{none:?}");
    }

    #[test]
    fn a_trigger_of_one_byte_or_none_is_left_alone() {
        let root = tempfile::tempdir().unwrap();
        let (port, sysfs) = fake_port(root.path(), "ttyS1", Some("1"));
        assert!(matches!(lower_for_tool(&port, &sysfs), FifoForTool::AsItIs));
        let (pty, sysfs) = fake_port(&root.path().join("b"), "pts3", None);
        assert!(matches!(lower_for_tool(&pty, &sysfs), FifoForTool::AsItIs));
    }
}
