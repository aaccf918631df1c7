"""Live figures: JSON status for the viewer and Prometheus metrics."""

from __future__ import annotations

from pathlib import PurePath

from fastapi import APIRouter, Depends, Request, Response

from cfsr_live.service.deps import HubDep, RuntimeDep, hide_paths, require_token
from cfsr_live.service.models import StatusModel

router = APIRouter(tags=["status"], dependencies=[Depends(require_token)])


@router.get("/api/status", response_model=StatusModel, summary="live figures and drop counters")
async def get_status(rt: RuntimeDep, hub: HubDep, request: Request) -> StatusModel:
    """Source, method, input steps/s, real-time factor, output fps, latency, and frames
    dropped at every stage: usb, replay, ring, worker, each client, recorder."""
    st = rt.status(hub)
    # the ring's file name only: an absolute server path tells a client nothing it can use
    # (the listing hides them too) and something about the machine it should not learn
    if st.ring.path is not None:
        st.ring = st.ring.model_copy(update={"path": PurePath(st.ring.path).name})
    settings = request.app.state.settings
    st.source = st.source.model_copy(
        update={"last_error": hide_paths(settings, st.source.last_error)})
    st.recording = st.recording.model_copy(
        update={"error": hide_paths(settings, st.recording.error)})
    return st


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

    return Response(generate_latest(request.app.state.metrics), media_type=CONTENT_TYPE_LATEST)


def make_registry(app):
    """A per-app Prometheus registry whose collector reads the runtime at scrape time."""
    from prometheus_client import CollectorRegistry
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    class _Collector:
        def collect(self):
            rt = getattr(app.state, "runtime", None)
            hub = getattr(app.state, "hub", None)
            if rt is None:
                return
            s = rt.status(hub)
            g = GaugeMetricFamily
            yield g("cfsr_input_steps_per_second", "steps/s entering the ring",
                    value=s.input_steps_per_s)
            yield g("cfsr_real_time_factor", "input rate / sensor rate",
                    value=s.real_time_factor)
            yield g("cfsr_output_fps", "frames/s published by the worker", value=s.output_fps)
            yield g("cfsr_latency_ms", "newest spike -> frame published (EMA)",
                    value=s.latency_ms)
            yield g("cfsr_compute_ms", "reconstruction time per frame (EMA)",
                    value=s.compute_ms)
            yield g("cfsr_clients", "connected viewer clients", value=s.clients)
            yield g("cfsr_worker_alive", "1 if the worker process runs",
                    value=float(s.worker.alive))
            yield g("cfsr_worker_steps_per_second", "steps/s the worker ingests",
                    value=s.worker.steps_per_s)
            c = CounterMetricFamily("cfsr_dropped_frames", "frames dropped, by stage",
                                    labels=["stage"])
            for stage in ("usb", "replay", "ring", "worker", "clients", "recorder"):
                c.add_metric([stage], float(getattr(s.drops, stage)))
            yield c
            c = CounterMetricFamily("cfsr_frames_published", "frames written into the ring")
            c.add_metric([], float(s.ring.frames_published))
            yield c
            c = CounterMetricFamily("cfsr_frames_out", "reconstructed frames published")
            c.add_metric([], float(s.worker.frames_out))
            yield c
            c = CounterMetricFamily("cfsr_worker_restarts", "worker restarts after a crash")
            c.add_metric([], float(s.worker.restarts))
            yield c
            usb = s.source.counters
            c = CounterMetricFamily("cfsr_source_events", "source error/recovery events",
                                    labels=["kind"])
            for k in ("timeouts", "stalls", "overflows", "short_blocks", "crc_errors",
                      "resyncs", "reconnects", "errors"):
                if k in usb:
                    c.add_metric([k], float(usb[k]))
            yield c

        def describe(self):
            return []

    reg = CollectorRegistry(auto_describe=False)
    reg.register(_Collector())
    return reg
