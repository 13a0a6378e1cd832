//! Basic authentication of the status server: one user, its password as a bcrypt hash in the
//! config. bcrypt is slow on purpose; credentials that passed once are remembered (a page keeps
//! sending the same header), and only one check runs at a time, so that a flood of wrong
//! passwords cannot take the small controller's CPU from the buses.

use std::sync::Mutex;

use base64::Engine as _;
use tokio::sync::Semaphore;

/// Remembered good `Authorization` headers (a few browsers and a scraper).
const REMEMBERED: usize = 8;

#[derive(Debug)]
pub struct BasicAuth {
    user: String,
    password_hash: String,
    accepted: Mutex<Vec<String>>,
    checking: Semaphore,
}

/// Equal in time that does not depend on where the first difference is.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl BasicAuth {
    pub fn new(user: &str, password_hash: &str) -> Self {
        Self {
            user: user.to_string(),
            password_hash: password_hash.to_string(),
            accepted: Mutex::new(Vec::new()),
            checking: Semaphore::new(1),
        }
    }

    fn remembered(&self, header: &str) -> bool {
        let accepted = self
            .accepted
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        // Every entry is compared, so the time tells nothing about which one matched.
        accepted.iter().fold(false, |found, known| {
            found | constant_time_eq(known.as_bytes(), header.as_bytes())
        })
    }

    /// Whether an `Authorization` header value carries this user and password.
    pub async fn check(&self, header: Option<&str>) -> bool {
        let Some(header) = header else {
            return false;
        };
        if self.remembered(header) {
            return true;
        }
        let Some((user, password)) = decode_basic(header) else {
            return false;
        };
        let Ok(_permit) = self.checking.acquire().await else {
            return false;
        };
        let hash = self.password_hash.clone();
        let verified = tokio::task::spawn_blocking(move || {
            bcrypt::verify(password.as_bytes(), &hash).unwrap_or(false)
        })
        .await
        .unwrap_or(false);
        let good = verified & constant_time_eq(user.as_bytes(), self.user.as_bytes());
        if good {
            let mut accepted = self
                .accepted
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            if accepted.len() == REMEMBERED {
                accepted.remove(0);
            }
            accepted.push(header.to_string());
        }
        good
    }
}

/// `Basic base64(user:password)` → (user, password).
fn decode_basic(header: &str) -> Option<(String, String)> {
    let encoded = header.strip_prefix("Basic ")?.trim();
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

    #[tokio::test]
    async fn accepts_the_user_and_password_only() {
        // Cost 4 keeps the test quick; the config's hash may have any cost.
        let hash = bcrypt::hash("s3cret", 4).unwrap();
        let auth = BasicAuth::new("admin", &hash);
        assert!(auth.check(Some(&header("admin", "s3cret"))).await);
        // Remembered now, still right.
        assert!(auth.check(Some(&header("admin", "s3cret"))).await);
        assert!(!auth.check(Some(&header("admin", "wrong"))).await);
        assert!(!auth.check(Some(&header("root", "s3cret"))).await);
        assert!(!auth.check(Some("Bearer x")).await);
        assert!(!auth.check(Some("Basic !!!")).await);
        assert!(!auth.check(None).await);
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
