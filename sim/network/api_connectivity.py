"""CAMARA Predictive Connectivity Data (v0.1.0) route of the emulated operator: its predictions from the
cell's radio map (sim/network/prediction.py), computed in a process of their own so that a large area
never stalls the cell's TTI loop."""

from __future__ import annotations

import time

from aiohttp import web

from dynqos.sim.network.control_http import answer, body
from dynqos.sim.network.operator import error
from dynqos.sim.network.operator_schema import problem
from dynqos.sim.network.prediction import Predictor, Refused
from dynqos.sim.network.prediction_process import PredictionProcess
from dynqos.sim.network.prediction_schema import RETRIEVE_CONNECTIVITY_STRICT

CONNECTIVITY_PREFIX = "/predictive-connectivity-data/v0.1"


class ConnectivityRoutes:
    def __init__(self, predictor: Predictor) -> None:
        self.predictor = predictor
        self.predictions = PredictionProcess()

    def start(self) -> None:
        self.predictions.start()  # before anyone asks: spawning it takes a second or so

    def close(self) -> None:
        self.predictions.close()

    def routes(self) -> list[web.RouteDef]:
        return [web.post(CONNECTIVITY_PREFIX + "/retrieve", self.connectivity)]

    async def connectivity(self, request: web.Request) -> web.Response:
        sent = await body(request)
        wrong = problem(RETRIEVE_CONNECTIVITY_STRICT, sent)
        if wrong is not None:
            return answer(error(400, "INVALID_ARGUMENT", wrong))
        try:
            text = await self.predictions.answer(self.predictor, sent, time.time())
        except Refused as refused:
            return answer(error(refused.status, refused.code, refused.message))
        return web.Response(body=text, content_type="application/json")
