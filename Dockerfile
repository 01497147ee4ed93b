# One image for every mtcw service: `docker run mtcw <acquire|worker|api|record|run|...>`.
FROM python:3.11-slim
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app
COPY pyproject.toml README.md ./
COPY mtcw_core ./mtcw_core
COPY services ./services
RUN pip install . && mkdir /keys /data && chown nobody /keys /data
USER nobody
ENTRYPOINT ["mtcw"]
CMD ["--help"]
