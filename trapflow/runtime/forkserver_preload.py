"""Imported by the fork server only (trapflow.runtime.forkserver.PRELOAD), never by a node
or the supervisor: its imports are what every node would import at start, and importing it
makes the server ignore SIGTERM (a stop of the whole process group is the supervisor's to
carry out; the server leaves when the supervisor does). Every node sets its own SIGTERM
handler at start (trapflow.runtime.node.node_main)."""

from __future__ import annotations

import os
import signal

import cv2
import msgspec
import numpy
import psutil
import yaml
import zmq

import trapflow.config.schema
import trapflow.runtime.node
import trapflow.wire.messages
import trapflow.wire.transport

SERVER_PID = os.getpid()
"""The fork server's pid: a node forked from it reads its parent's pid here."""

signal.signal(signal.SIGTERM, signal.SIG_IGN)

LOADED = (cv2, msgspec, numpy, psutil, yaml, zmq, trapflow.config.schema, trapflow.runtime.node,
          trapflow.wire.messages, trapflow.wire.transport)
