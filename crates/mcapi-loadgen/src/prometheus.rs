//! The server's Prometheus text (its `/metrics`): the request-duration
//! histogram of one route, and the bucket bound under which a quantile of
//! the requests counted between two scrapes fell.

use anyhow::{Result, ensure};
use hyper::{Method, StatusCode};

use crate::http::{HttpConn, HttpTarget};

/// The server's request-duration histogram of one route (status 200, all
/// methods) from `/metrics`: cumulative count per bucket bound in seconds.
pub(crate) async fn route_histogram(http: &HttpTarget, route: &str) -> Result<Vec<(f64, f64)>> {
    let mut conn = HttpConn::connect(http).await?;
    let (status, body) = conn.send(Method::GET, "/metrics", None).await?;
    ensure!(status == StatusCode::OK, "/metrics: {status}");
    let text = String::from_utf8_lossy(&body);
    let route = format!("route=\"{route}\"");
    let mut buckets: Vec<(f64, f64)> = Vec::new();
    for line in text.lines() {
        let Some(rest) = line.strip_prefix("mcapi_http_request_duration_seconds_bucket{") else {
            continue;
        };
        let Some((labels, count)) = rest.rsplit_once("} ") else {
            continue;
        };
        if !labels.contains(&route) || !labels.contains("status=\"200\"") {
            continue;
        }
        let Some(le) = labels
            .split("le=\"")
            .nth(1)
            .and_then(|l| l.split('"').next())
        else {
            continue;
        };
        let le = if le == "+Inf" {
            f64::INFINITY
        } else {
            le.parse()?
        };
        let count: f64 = count.trim().parse()?;
        match buckets.iter_mut().find(|(b, _)| *b == le) {
            Some((_, c)) => *c += count,
            None => buckets.push((le, count)),
        }
    }
    buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(buckets)
}

/// The bucket bound under which a fraction `q` of the requests counted
/// between two scrapes fell.
pub(crate) fn histogram_quantile(
    before: &[(f64, f64)],
    after: &[(f64, f64)],
    q: f64,
) -> Option<f64> {
    let delta = |le: f64, count: f64| {
        count
            - before
                .iter()
                .find(|(b, _)| *b == le)
                .map_or(0.0, |(_, c)| *c)
    };
    let total = after.last().map(|&(le, c)| delta(le, c))?;
    if total <= 0.0 {
        return None;
    }
    after
        .iter()
        .find(|&&(le, c)| delta(le, c) >= q * total)
        .map(|&(le, _)| le)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_of_a_scraped_histogram() {
        let before = [(0.001, 10.0), (0.01, 10.0), (f64::INFINITY, 10.0)];
        let after = [(0.001, 60.0), (0.01, 109.0), (f64::INFINITY, 110.0)];
        // 100 new requests: 50 under 1 ms, 49 more under 10 ms, one slower.
        assert_eq!(histogram_quantile(&before, &after, 0.5), Some(0.001));
        assert_eq!(histogram_quantile(&before, &after, 0.99), Some(0.01));
        assert_eq!(
            histogram_quantile(&before, &after, 1.0),
            Some(f64::INFINITY)
        );
        assert_eq!(histogram_quantile(&after, &after, 0.5), None);
    }
}
