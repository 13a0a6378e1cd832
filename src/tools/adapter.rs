//! What sits between a serial port and the RS-485 line, and how late it can hand a reply over.
//!
//! An empty port setting costs a scan its first-byte timeout plus this allowance, 48 times over,
//! so one fixed allowance big enough for the slowest USB adapter (wb-mqtt-serial adds 24 ms)
//! doubles a full scan on a controller's own UART. The kernel says which kind of port it is:
//! `/sys/class/tty/<name>/device` is a USB serial device for adapters, and FTDI chips expose
//! their latency timer there (the longest they hold received bytes before sending them on).

use std::fs;
use std::path::Path;
use std::time::Duration;

use crate::transport::fifo::{read_number, tty_dir};

/// What the kernel tells about a port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Adapter {
    /// A USB adapter with a latency timer (FTDI): it holds bytes up to that long.
    UsbWithLatencyTimer { latency_timer_ms: u64 },
    /// Another USB adapter (CH340, CP210x, PL2303, CDC-ACM): its delay is not published.
    Usb,
    /// A UART of the machine itself, a pseudo-terminal, or anything the kernel does not
    /// describe as USB: bytes arrive as the line delivers them.
    Native,
}

/// Added for a USB adapter that does not say its delay: wb-mqtt-serial's allowance.
const UNKNOWN_USB_ALLOWANCE: Duration = Duration::from_millis(24);
/// Added on top of an FTDI latency timer: the USB frame and the machine's scheduling.
const USB_MARGIN: Duration = Duration::from_millis(4);
/// A native UART or a pseudo-terminal: the kernel's tty hand-over and a busy machine.
const NATIVE_ALLOWANCE: Duration = Duration::from_millis(5);

impl Adapter {
    /// What the port at `path` is, read from sysfs (`sysfs_tty`: `/sys/class/tty` outside
    /// tests). Symbolic links (`/dev/ttyRS485-1`) are followed to the device node.
    pub fn detect(path: &Path, sysfs_tty: &Path) -> Adapter {
        let Some(device) = tty_dir(path, sysfs_tty).map(|dir| dir.join("device")) else {
            return Adapter::Native;
        };
        if let Some(ms) = read_number(&device.join("latency_timer")) {
            return Adapter::UsbWithLatencyTimer {
                latency_timer_ms: ms,
            };
        }
        if is_usb(&device) {
            Adapter::Usb
        } else {
            Adapter::Native
        }
    }

    /// How late a reply may reach the tool after it left the device.
    pub fn reply_allowance(self) -> Duration {
        match self {
            Adapter::UsbWithLatencyTimer { latency_timer_ms } => {
                Duration::from_millis(latency_timer_ms) + USB_MARGIN
            }
            Adapter::Usb => UNKNOWN_USB_ALLOWANCE,
            Adapter::Native => NATIVE_ALLOWANCE,
        }
    }

    /// For the operator: which allowance was chosen and why.
    pub fn describe(self) -> String {
        let ms = self.reply_allowance().as_millis();
        match self {
            Adapter::UsbWithLatencyTimer { latency_timer_ms } => format!(
                "USB adapter with a {latency_timer_ms} ms latency timer: {ms} ms allowed for \
                 each reply to arrive"
            ),
            Adapter::Usb => format!("USB adapter: {ms} ms allowed for each reply to arrive"),
            Adapter::Native => format!("{ms} ms allowed for each reply to arrive"),
        }
    }
}

/// A USB serial driver (`usb-serial` bus) or a CDC-ACM interface (`usb` bus) owns the device.
fn is_usb(device: &Path) -> bool {
    fs::read_link(device.join("subsystem"))
        .ok()
        .and_then(|subsystem| {
            subsystem
                .file_name()
                .map(|name| name.to_string_lossy().starts_with("usb"))
        })
        .unwrap_or(false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;
    use std::path::PathBuf;

    /// A fake `/sys/class/tty` with one device `name` on `bus`, and its `/dev` node.
    fn fake_port(
        root: &Path,
        name: &str,
        bus: &str,
        latency_timer: Option<&str>,
    ) -> (PathBuf, PathBuf) {
        let bus_dir = root.join("bus").join(bus);
        fs::create_dir_all(&bus_dir).unwrap();
        let device = root.join("sys/class/tty").join(name).join("device");
        fs::create_dir_all(&device).unwrap();
        symlink(&bus_dir, device.join("subsystem")).unwrap();
        if let Some(value) = latency_timer {
            fs::write(device.join("latency_timer"), value).unwrap();
        }
        let dev = root.join("dev");
        fs::create_dir_all(&dev).unwrap();
        let node = dev.join(name);
        fs::write(&node, "").unwrap();
        (root.join("sys/class/tty"), node)
    }

    #[test]
    fn an_ftdi_adapter_is_given_its_latency_timer_and_a_margin() {
        let root = tempfile::tempdir().unwrap();
        let (sysfs, node) = fake_port(root.path(), "ttyUSB0", "usb-serial", Some("16\n"));
        let adapter = Adapter::detect(&node, &sysfs);
        assert_eq!(
            adapter,
            Adapter::UsbWithLatencyTimer {
                latency_timer_ms: 16
            }
        );
        assert_eq!(adapter.reply_allowance(), Duration::from_millis(20));
        // A timer set to 1 ms (low_latency) makes the scan nearly as quick as a native UART.
        let (sysfs, node) = fake_port(root.path(), "ttyUSB1", "usb-serial", Some("1"));
        assert_eq!(
            Adapter::detect(&node, &sysfs).reply_allowance(),
            Duration::from_millis(5)
        );
    }

    #[test]
    fn other_usb_adapters_get_the_wb_mqtt_serial_allowance() {
        let root = tempfile::tempdir().unwrap();
        let (sysfs, node) = fake_port(root.path(), "ttyUSB0", "usb-serial", None);
        assert_eq!(Adapter::detect(&node, &sysfs), Adapter::Usb);
        let (sysfs, node) = fake_port(root.path(), "ttyACM0", "usb", None);
        assert_eq!(Adapter::detect(&node, &sysfs), Adapter::Usb);
        assert_eq!(Adapter::Usb.reply_allowance(), Duration::from_millis(24));
    }

    #[test]
    fn a_native_uart_reached_through_a_symlink_is_native() {
        let root = tempfile::tempdir().unwrap();
        let (sysfs, node) = fake_port(root.path(), "ttymxc3", "platform", None);
        let link = root.path().join("ttyRS485-1");
        symlink(&node, &link).unwrap();
        assert_eq!(Adapter::detect(&link, &sysfs), Adapter::Native);
        assert_eq!(Adapter::Native.reply_allowance(), Duration::from_millis(5));
    }

    #[test]
    fn a_port_sysfs_does_not_know_is_native() {
        let root = tempfile::tempdir().unwrap();
        let node = root.path().join("pts-7");
        fs::write(&node, "").unwrap();
        assert_eq!(
            Adapter::detect(&node, &root.path().join("nothing")),
            Adapter::Native
        );
        // A garbled latency_timer is not trusted; the bus decides.
        let (sysfs, node) = fake_port(root.path(), "ttyUSB2", "usb-serial", Some("fast"));
        assert_eq!(Adapter::detect(&node, &sysfs), Adapter::Usb);
    }
}
