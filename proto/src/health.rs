//! The standard gRPC health protocol (`grpc.health.v1`) beside each rfcl service, for container
//! engines' probes: Kubernetes' `grpc:` probes and `rfcl-health` in Compose healthchecks. It needs
//! no token (see [`crate::auth`]): it says only whether a service is serving.
use std::time::Duration;

use tonic::transport::Endpoint;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;
pub use tonic_health::server::{health_reporter, HealthReporter};

/// Marks the service named `name` (a tonic `NamedService::NAME`, e.g. `rfcl.v1.Curriculum`) and the
/// server as a whole (the empty name, which probes ask by default) as serving.
pub async fn serving(reporter: &HealthReporter, name: &str) {
    reporter
        .set_service_status(name, tonic_health::ServingStatus::Serving)
        .await;
    reporter
        .set_service_status("", tonic_health::ServingStatus::Serving)
        .await;
}

/// Asks `endpoint` whether `service` (empty: the server as a whole) is serving.
pub async fn check(endpoint: Endpoint, service: &str, timeout: Duration) -> Result<bool, String> {
    let channel = endpoint
        .connect_timeout(timeout)
        .timeout(timeout)
        .connect()
        .await
        .map_err(|e| format!("connecting: {e}"))?;
    let reply = HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: service.to_string(),
        })
        .await
        .map_err(|s| format!("{}: {}", s.code(), s.message()))?;
    Ok(reply.into_inner().status == ServingStatus::Serving as i32)
}
