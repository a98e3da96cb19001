"""The service: settings (the only defaults of a deployment), the composition root, metrics, the HTTP
app and the gRPC server, and the streams they answer."""
