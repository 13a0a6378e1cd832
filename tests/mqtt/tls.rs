//! The MQTT side over TLS against a real mosquitto TLS listener with a test CA made here
//! (openssl): server verified by our CA, client certificate required by the broker. Proves the
//! ring-only rustls build connects, and that values arrive.

use rtu2mqtt::child::StopWithParent;
use std::path::Path;
use std::process::{Child, Command, Stdio};

use crate::mqtt_support::{
    free_port, retained, settings, template_device, value, wait_for, MqttUnderTest,
};
use rtu2mqtt::config::config_file::TlsConfig;
use rtu2mqtt::device_updates::DeviceUpdate;

fn openssl(dir: &Path, args: &[&str]) {
    let out = Command::new("openssl")
        .args(args)
        .current_dir(dir)
        .output()
        .expect("this test needs openssl (apt-get install openssl; scripts/test does it)");
    assert!(
        out.status.success(),
        "openssl {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A CA, a server certificate for 127.0.0.1 and a client certificate, all signed by the CA.
fn make_pki(dir: &Path) {
    openssl(
        dir,
        &[
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "2",
            "-subj",
            "/CN=rtu2mqtt test CA",
            "-keyout",
            "ca.key",
            "-out",
            "ca.crt",
        ],
    );
    // Extensions make v3 certificates; webpki refuses v1 ones.
    std::fs::write(dir.join("server.ext"), "subjectAltName=IP:127.0.0.1\n").unwrap();
    std::fs::write(dir.join("client.ext"), "extendedKeyUsage=clientAuth\n").unwrap();
    for (name, ext) in [("server", "server.ext"), ("client", "client.ext")] {
        openssl(
            dir,
            &[
                "req",
                "-newkey",
                "rsa:2048",
                "-nodes",
                "-subj",
                &format!("/CN={name}"),
                "-keyout",
                &format!("{name}.key"),
                "-out",
                &format!("{name}.csr"),
            ],
        );
        let mut sign = vec![
            "x509".to_owned(),
            "-req".into(),
            "-in".into(),
            format!("{name}.csr"),
            "-CA".into(),
            "ca.crt".into(),
            "-CAkey".into(),
            "ca.key".into(),
            "-CAcreateserial".into(),
            "-days".into(),
            "2".into(),
            "-out".into(),
            format!("{name}.crt"),
        ];
        sign.extend(["-extfile".to_owned(), ext.to_owned()]);
        let sign: Vec<&str> = sign.iter().map(String::as_str).collect();
        openssl(dir, &sign);
    }
}

struct TlsBroker(Child);

impl Drop for TlsBroker {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publishes_through_a_tls_listener_with_a_client_certificate() {
    let dir = tempfile::tempdir().unwrap();
    make_pki(dir.path());
    let tls_port = free_port();
    let plain_port = free_port();
    let d = dir.path().display();
    // Run as root, mosquitto would drop to its own user, which cannot read our 0600 keys.
    let user = if std::os::unix::fs::MetadataExt::uid(&std::fs::metadata(dir.path()).unwrap()) == 0
    {
        "user root\n"
    } else {
        ""
    };
    std::fs::write(
        dir.path().join("mosquitto.conf"),
        format!(
            "{user}per_listener_settings false\nallow_anonymous true\npersistence false\n\
             listener {plain_port} 127.0.0.1\n\
             listener {tls_port} 127.0.0.1\ncafile {d}/ca.crt\ncertfile {d}/server.crt\n\
             keyfile {d}/server.key\nrequire_certificate true\n"
        ),
    )
    .unwrap();
    let _broker = TlsBroker(
        Command::new(crate::mqtt_support::mosquitto_program("mosquitto"))
            .stop_with_parent()
            .arg("-c")
            .arg(dir.path().join("mosquitto.conf"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );

    let mut tls_settings = settings(tls_port);
    tls_settings.broker.tls = Some(TlsConfig {
        ca_file: Some(dir.path().join("ca.crt")),
        cert_file: Some(dir.path().join("client.crt")),
        key_file: Some(dir.path().join("client.key")),
    });
    let mqtt = MqttUnderTest::start(tls_settings);
    mqtt.send(DeviceUpdate::Added(template_device("rtu2mqtt-climate", 2)))
        .await;
    mqtt.send(value("climate_2", "Temperature", "21.5")).await;
    // Read back through the plain listener of the same broker.
    wait_for("the value published over TLS", || async {
        let state = retained(plain_port).await?;
        (state.get("/devices/climate_2/controls/Temperature")? == "21.5").then_some(())
    })
    .await;
    assert!(mqtt.is_running());
    mqtt.stop().await;
}
