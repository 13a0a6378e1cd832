//! Basic authentication of the status server: one user, its password as a bcrypt hash in the
//! config. bcrypt is slow on purpose, so that a flood of wrong passwords cannot take the small
//! controller's CPU from the buses:
//!
//! - credentials that passed once are remembered (a page keeps sending the same header) and pass
//!   at once, whatever else is going on;
//! - one check runs at a time; a request with other credentials that arrives meanwhile is not
//!   queued but answered at once ([`Verdict::Busy`], 429 with `Retry-After`);
//! - after wrong passwords, the next check of credentials not seen before starts only
//!   [`FIRST_BACKOFF`] after the failure, doubling with each further one in a row up to
//!   [`MAX_BACKOFF`]; a check that passes ends it.

use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use base64::Engine as _;
use tokio::sync::Semaphore;
use tokio::time::Instant;
use tracing::warn;

/// Remembered good `Authorization` headers (a few browsers and a scraper).
const REMEMBERED: usize = 8;
/// The wait after one wrong password before the next check of credentials not seen before.
pub const FIRST_BACKOFF: Duration = Duration::from_millis(500);
/// The longest wait, however many wrong passwords came in a row.
pub const MAX_BACKOFF: Duration = Duration::from_secs(4);
/// A hash of a lower cost is named in the log at start: cheap to guess.
const MIN_COST: u32 = 10;

/// Whether a password matches a bcrypt hash (bcrypt's, but for tests).
type Verifier = Arc<dyn Fn(&str, &str) -> bool + Send + Sync>;

/// What a request's credentials get.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Accepted,
    /// Wrong, missing or malformed.
    Refused,
    /// Not checked: another check runs (or waits out the back-off); try again after this.
    Busy {
        retry_after: Duration,
    },
}

/// Wrong passwords in a row, and when the next check of unknown credentials may start.
#[derive(Debug, Default)]
struct Failures {
    in_a_row: u32,
    next_check: Option<Instant>,
}

pub struct BasicAuth {
    user: String,
    password_hash: String,
    accepted: Mutex<Vec<String>>,
    failures: Mutex<Failures>,
    /// One permit: the check that runs (or waits out the back-off) holds it.
    checking: Arc<Semaphore>,
    verify: Verifier,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Equal in time that does not depend on where the first difference is.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The cost of a bcrypt hash (`$2b$12$…` → 12).
fn bcrypt_cost(hash: &str) -> Option<u32> {
    let mut parts = hash.split('$');
    parts.next().filter(|before| before.is_empty())?;
    parts.next()?;
    parts.next()?.parse().ok()
}

/// The wait before the next check of unknown credentials after `in_a_row` wrong passwords.
fn backoff(in_a_row: u32) -> Duration {
    match in_a_row {
        0 => Duration::ZERO,
        n => FIRST_BACKOFF
            .saturating_mul(1 << (n - 1).min(16))
            .min(MAX_BACKOFF),
    }
}

impl BasicAuth {
    /// Made once, when the server starts: a hash of a cost below 10 is named in the log then.
    pub fn new(user: &str, password_hash: &str) -> Self {
        if let Some(cost) = bcrypt_cost(password_hash).filter(|cost| *cost < MIN_COST) {
            warn!(
                "http.password_hash has bcrypt cost {cost}: cheap to guess; make a new hash with \
                 `rtu2mqtt hash-password` (cost 12) or `htpasswd -nbBC 12 {user} PASSWORD`"
            );
        }
        Self::without_warning(user, password_hash)
    }

    /// [`Self::new`] without the log line (tests: tracing caches a log line's interest across
    /// threads, so only the test that reads the log may reach it).
    fn without_warning(user: &str, password_hash: &str) -> Self {
        Self {
            user: user.to_string(),
            password_hash: password_hash.to_string(),
            accepted: Mutex::new(Vec::new()),
            failures: Mutex::new(Failures::default()),
            checking: Arc::new(Semaphore::new(1)),
            verify: Arc::new(|password, hash| {
                bcrypt::verify(password.as_bytes(), hash).unwrap_or(false)
            }),
        }
    }

    /// [`Self::new`] with `verify` in place of bcrypt.
    #[cfg(test)]
    fn with_verifier(
        user: &str,
        verify: impl Fn(&str, &str) -> bool + Send + Sync + 'static,
    ) -> Self {
        Self {
            verify: Arc::new(verify),
            ..Self::without_warning(user, "")
        }
    }

    fn remembered(&self, header: &str) -> bool {
        let accepted = lock(&self.accepted);
        // Every entry is compared, so the time tells nothing about which one matched.
        accepted.iter().fold(false, |found, known| {
            found | constant_time_eq(known.as_bytes(), header.as_bytes())
        })
    }

    /// What to tell a request that came while a check runs: the back-off left, at least 1 s.
    fn retry_after(&self) -> Duration {
        let next_check = lock(&self.failures).next_check;
        let left = next_check
            .map(|at| at.saturating_duration_since(Instant::now()))
            .unwrap_or_default();
        Duration::from_secs(left.as_secs_f64().ceil().max(1.0) as u64)
    }

    /// Whether an `Authorization` header value carries this user and password.
    pub async fn check(&self, header: Option<&str>) -> Verdict {
        let Some(header) = header else {
            return Verdict::Refused;
        };
        if self.remembered(header) {
            return Verdict::Accepted;
        }
        let Some((user, password)) = decode_basic(header) else {
            return Verdict::Refused;
        };
        let Ok(permit) = Arc::clone(&self.checking).try_acquire_owned() else {
            return Verdict::Busy {
                retry_after: self.retry_after(),
            };
        };
        let next_check = lock(&self.failures).next_check;
        if let Some(at) = next_check {
            tokio::time::sleep_until(at).await;
        }
        let hash = self.password_hash.clone();
        let verify = Arc::clone(&self.verify);
        // The permit goes with the bcrypt run: a client that hangs up meanwhile does not let
        // another check start before it is done.
        let Ok((verified, _permit)) =
            tokio::task::spawn_blocking(move || (verify(&password, &hash), permit)).await
        else {
            return Verdict::Refused;
        };
        let good = verified & constant_time_eq(user.as_bytes(), self.user.as_bytes());
        let mut failures = lock(&self.failures);
        if good {
            *failures = Failures::default();
            drop(failures);
            let mut accepted = lock(&self.accepted);
            if accepted.len() == REMEMBERED {
                accepted.remove(0);
            }
            accepted.push(header.to_string());
            Verdict::Accepted
        } else {
            failures.in_a_row = failures.in_a_row.saturating_add(1);
            failures.next_check = Some(Instant::now() + backoff(failures.in_a_row));
            Verdict::Refused
        }
    }
}

/// `Basic base64(user:password)` → (user, password).
fn decode_basic(header: &str) -> Option<(String, String)> {
    // The scheme's name is case-insensitive (RFC 7617).
    let (scheme, encoded) = header.trim_start().split_once(' ')?;
    if !scheme.eq_ignore_ascii_case("basic") {
        return None;
    }
    let encoded = encoded.trim();
    let decoded = base64::engine::general_purpose::STANDARD
        .decode(encoded)
        .ok()?;
    let text = String::from_utf8(decoded).ok()?;
    let (user, password) = text.split_once(':')?;
    Some((user.to_string(), password.to_string()))
}

/// The bcrypt hash of `password` for the config's `password_hash`.
pub fn hash_password(password: &str) -> Result<String, bcrypt::BcryptError> {
    bcrypt::hash(password, bcrypt::DEFAULT_COST)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(user: &str, password: &str) -> String {
        let encoded =
            base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
        format!("Basic {encoded}")
    }

    // Paused clock: the second wrong password waits out the back-off without real waiting.
    #[tokio::test(start_paused = true)]
    async fn accepts_the_user_and_password_only() {
        // Cost 4 keeps the test quick; the config's hash may have any cost.
        let hash = bcrypt::hash("s3cret", 4).unwrap();
        let auth = BasicAuth::without_warning("admin", &hash);
        let accepted = Verdict::Accepted;
        assert_eq!(auth.check(Some(&header("admin", "s3cret"))).await, accepted);
        // Remembered now, still right.
        assert_eq!(auth.check(Some(&header("admin", "s3cret"))).await, accepted);
        let refused = Verdict::Refused;
        assert_eq!(auth.check(Some(&header("admin", "wrong"))).await, refused);
        assert_eq!(auth.check(Some(&header("root", "s3cret"))).await, refused);
        assert_eq!(auth.check(Some("Bearer x")).await, refused);
        assert_eq!(auth.check(Some("Basic !!!")).await, refused);
        assert_eq!(auth.check(None).await, refused);
    }

    /// The scheme's name is case-insensitive (RFC 7617): `basic` and `BASIC` are Basic.
    #[test]
    fn the_scheme_name_is_case_insensitive() {
        let encoded = base64::engine::general_purpose::STANDARD.encode("admin:s3cret");
        for scheme in ["Basic", "basic", "BASIC"] {
            assert_eq!(
                decode_basic(&format!("{scheme} {encoded}")),
                Some(("admin".to_string(), "s3cret".to_string())),
                "{scheme}"
            );
        }
        assert_eq!(decode_basic(&format!("Bearer {encoded}")), None);
        assert_eq!(decode_basic("Basic"), None);
    }

    /// While a check runs, a request with credentials not seen before is answered at once
    /// (not queued); remembered credentials pass; requests without (valid) credentials are
    /// refused as before. The "bcrypt" here waits until the test lets it finish.
    #[tokio::test(start_paused = true)]
    async fn a_running_check_answers_other_new_credentials_at_once() {
        let (entered, mut running) = tokio::sync::mpsc::unbounded_channel();
        let (finish, finished) = std::sync::mpsc::channel::<()>();
        let finished = Mutex::new(finished);
        let auth = Arc::new(BasicAuth::with_verifier("admin", move |password, _hash| {
            if password == "slow" {
                entered.send(()).unwrap();
                finished.lock().unwrap().recv().unwrap();
            }
            password == "s3cret"
        }));
        let good = header("admin", "s3cret");
        assert!(passes(&auth, &good).await);
        let slow = tokio::spawn({
            let auth = Arc::clone(&auth);
            async move { auth.check(Some(&header("admin", "slow"))).await }
        });
        running.recv().await.unwrap();
        let busy = Verdict::Busy {
            retry_after: Duration::from_secs(1),
        };
        assert_eq!(auth.check(Some(&header("admin", "guess"))).await, busy);
        // The right password from a browser not seen before waits for its turn too.
        assert_eq!(auth.check(Some(&format!("{good} "))).await, busy);
        assert_eq!(auth.check(Some(&good)).await, Verdict::Accepted);
        assert_eq!(auth.check(None).await, Verdict::Refused);
        assert_eq!(auth.check(Some("Basic !!!")).await, Verdict::Refused);
        finish.send(()).unwrap();
        assert_eq!(slow.await.unwrap(), Verdict::Refused);
        // Free again: the next one is checked (after the back-off of the wrong one).
        assert_eq!(
            auth.check(Some(&format!("{good} "))).await,
            Verdict::Accepted
        );
    }

    /// While a check waits out the back-off, others are told how long is left.
    #[tokio::test(start_paused = true)]
    async fn the_answer_to_a_busy_request_says_when_to_come_back() {
        let auth = Arc::new(BasicAuth::with_verifier("admin", |password, _| {
            password == "s3cret"
        }));
        for _ in 0..4 {
            assert!(!passes(&auth, &header("admin", "guess")).await);
        }
        // The fifth wrong password waits 4 s from the fourth failure.
        let waiting = tokio::spawn({
            let auth = Arc::clone(&auth);
            async move { auth.check(Some(&header("admin", "guess"))).await }
        });
        tokio::task::yield_now().await;
        tokio::time::advance(Duration::from_millis(1500)).await;
        assert_eq!(
            auth.check(Some(&header("admin", "s3cret"))).await,
            Verdict::Busy {
                retry_after: Duration::from_secs(3)
            }
        );
        assert_eq!(waiting.await.unwrap(), Verdict::Refused);
    }

    /// Whether the check let `header` in.
    async fn passes(auth: &BasicAuth, header: &str) -> bool {
        auth.check(Some(header)).await == Verdict::Accepted
    }

    /// Each wrong password makes the next check of credentials not seen before wait longer
    /// (0.5 s, doubling, at most 4 s after the failure), until a check passes. A browser that
    /// logged in before never waits. The clock is tokio's paused one: only the waits move it.
    #[tokio::test(start_paused = true)]
    async fn wrong_passwords_slow_down_further_checks_of_unknown_credentials() {
        let hash = bcrypt::hash("s3cret", 4).unwrap();
        let auth = BasicAuth::without_warning("admin", &hash);
        let good = header("admin", "s3cret");
        assert!(passes(&auth, &good).await);
        let wrong = header("admin", "guess");
        let mut waited = Vec::new();
        for _ in 0..6 {
            let started = Instant::now();
            assert!(!passes(&auth, &wrong).await);
            waited.push(started.elapsed().as_millis());
            let started = Instant::now();
            assert!(passes(&auth, &good).await);
            assert_eq!(
                started.elapsed(),
                Duration::ZERO,
                "the remembered login waited"
            );
        }
        let expected = [0, 500, 1000, 2000, 4000, 4000];
        assert!(
            waited
                .iter()
                .zip(expected)
                .all(|(w, e)| (e..e + 10).contains(w)),
            "waited {waited:?} ms, expected {expected:?}"
        );
        // The right password in a header not seen before (another browser) waits its turn too,
        // and its success ends the back-off.
        let started = Instant::now();
        assert!(passes(&auth, &format!("{good} ")).await);
        assert!((4000..4010).contains(&started.elapsed().as_millis()));
        let started = Instant::now();
        assert!(!passes(&auth, &wrong).await);
        assert_eq!(started.elapsed(), Duration::ZERO);
    }

    /// Writes what the subscriber logs into a buffer the test reads.
    #[derive(Clone, Default)]
    struct Captured(Arc<Mutex<Vec<u8>>>);

    impl std::io::Write for Captured {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// A hash of cost below 10 is named at start, once: not on every check.
    #[tokio::test(start_paused = true)]
    async fn a_cheap_hash_is_warned_about_once() {
        let captured = Captured::default();
        let writer = captured.clone();
        let subscriber = tracing_subscriber::fmt()
            .with_writer(move || writer.clone())
            .with_ansi(false)
            .finish();
        let _default = tracing::subscriber::set_default(subscriber);
        let cheap = BasicAuth::new("admin", &bcrypt::hash("s3cret", 4).unwrap());
        for _ in 0..3 {
            assert!(passes(&cheap, &header("admin", "s3cret")).await);
            assert!(!passes(&cheap, &header("admin", "guess")).await);
        }
        // Cost 10 and 12: not warned about (built by hand: no check runs).
        let _ = BasicAuth::new("admin", &format!("$2b$10${}", "a".repeat(53)));
        let _ = BasicAuth::new("admin", &format!("$2y$12${}", "a".repeat(53)));
        let log = String::from_utf8(captured.0.lock().unwrap().clone()).unwrap();
        let warnings: Vec<&str> = log.lines().filter(|l| l.contains("WARN")).collect();
        assert_eq!(warnings.len(), 1, "{log}");
        assert!(
            warnings[0].contains("cost 4") && warnings[0].contains("cheap to guess"),
            "{log}"
        );
    }

    #[test]
    fn verifies_hashes_of_other_tools() {
        // Made by glibc's crypt(3) (`$2b$`), an implementation independent of ours; htpasswd
        // writes the same hash with the `$2y$` prefix.
        let hash = "$2b$05$dCQ30UB4jly1BFDuIxBRAuNZQfUjMqCDKeE1BLR1sstX/KO5QMpFK";
        assert!(bcrypt::verify("s3cret", hash).unwrap());
        assert!(bcrypt::verify("s3cret", &hash.replace("$2b$", "$2y$")).unwrap());
        assert!(!bcrypt::verify("s3cret!", hash).unwrap());
    }
}
