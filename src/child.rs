//! Processes this binary starts for itself (the demo's simulator, the bench's simulator, broker
//! and daemon) stop when it does, however it ends: killed, crashed or interrupted, not only when
//! it gets to stop them itself.

use std::os::unix::process::CommandExt;
use std::process::Command;

/// Makes a command's process get SIGTERM when the thread that spawns it ends (Linux's
/// `PR_SET_PDEATHSIG`: the signal follows the spawning *thread*, so spawn from a thread that
/// lives as long as the child should).
pub trait StopWithParent {
    fn stop_with_parent(&mut self) -> &mut Self;
}

impl StopWithParent for Command {
    fn stop_with_parent(&mut self) -> &mut Self {
        let parent = std::process::id();
        // SAFETY: the closure runs in the child between fork and exec and calls only prctl,
        // getppid and raise, which are async-signal-safe; it allocates nothing.
        unsafe {
            self.pre_exec(move || {
                use nix::libc;
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM, 0, 0, 0) == -1 {
                    return Err(std::io::Error::last_os_error());
                }
                // The parent may have ended before the request above was made.
                if u32::try_from(libc::getppid()).ok() != Some(parent) {
                    libc::raise(libc::SIGTERM);
                }
                Ok(())
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_child_stops_when_the_thread_that_started_it_ends() {
        use std::os::unix::process::ExitStatusExt;
        let mut child = std::thread::spawn(|| {
            Command::new("sleep")
                .arg("30")
                .stop_with_parent()
                .spawn()
                .expect("sleep starts")
        })
        .join()
        .expect("the spawning thread");
        // The spawning thread has ended: the child got SIGTERM (without it, it would sleep its
        // 30 s and exit normally).
        let status = child.wait().expect("waits for it");
        assert_eq!(status.signal(), Some(nix::libc::SIGTERM), "{status:?}");
    }
}
